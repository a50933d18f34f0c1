"""What the experiments are: scales, grids, rendered pools, runs, and the plan of a sweep.

:func:`plan` turns resolved :class:`Options` into the ordered list of :class:`RunSpec` (grid point x seed),
each with its :class:`PoolSpec` (the rendered dataset its frames come from) and its training configuration,
built in one place, :func:`train_config`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from s3k.base.choices import Device
from s3k.base.errors import UserError
from s3k.config import TrainConfig

#: The paper's image size (pixels) and training length (batches).
PAPER_SIZE = 400
PAPER_STEPS = 150_000

#: Paper, sec. 4.3 table: test rms error (pixels at 400 px) on the held-out instances per training instances.
PAPER_CATEGORY_TEST_PX = {1: 26.99, 2: 14.65, 3: 16.22, 6: 15.05, 8: 11.75, 12: 10.77}

#: Millimetres per pixel of the paper's images: the paper states that at 400 px one pixel is about 2.8 mm at
#: its workspace centre. Its pixel figures compare with s3k's only in millimetres (s3k's scenes have other
#: cameras and image sizes), so they are converted with this.
PAPER_MM_PER_PX = 2.8

#: The simulated scene of each experiment: its pixel size at the runs' image size turns their pixel errors
#: into millimetres.
EXPERIMENT_SCENES = {"label-efficiency": "box", "domain-shift": "distractors", "category": "category",
                     "alpha": "box"}

#: How a run's labelled frames are chosen from its pool: "random" (stratified over segments or instances,
#: :func:`s3k.experiments.views.stratified_pick`), "coverage" or "representative" (the labelling app's pose
#: orders, :func:`s3k.experiments.views.pose_pick`).
LABEL_CHOICES = ("random", "coverage", "representative")

#: Files of the workspace layout (see the package documentation).
RESULT_FILE = "result.json"
SUMMARY_FILE = "summary.json"


# ------------------------------------------------------------------------------------------------------------
# Scales and grids


@dataclass(frozen=True)
class Scale:
    """Sizes shared by every experiment at one scale.

    Attributes:
        size: image width and height in pixels (rendered at this size; the network sees it unchanged).
        steps: optimizer steps per run.
        test: test frames per dataset.
        pool_labelled: labelled frames rendered per box / distractors dataset (runs pick subsets).
        pool_unlabelled: unlabelled frames rendered per dataset.
        seeds: seeds at the points that carry a claim; other points get one seed.
        train: further TrainConfig fields of this scale (e.g. a smaller network for tests).
        crop_size: the refining pass's input in pixels when the runs train two passes.
    """

    size: int
    steps: int
    test: int
    pool_labelled: int
    pool_unlabelled: int
    seeds: int
    train: dict[str, Any] = field(default_factory=dict)
    crop_size: int = 128


SCALES: dict[str, Scale] = {
    # seconds per experiment; what the tests run
    "toy": Scale(size=32, steps=2, test=2, pool_labelled=3, pool_unlabelled=4, seeds=1,
                 train={"channels": (8, 16, 16), "res_blocks": 1, "batch_labelled": 2, "batch_unlabelled": 2,
                        "val_every": 0, "checkpoint_every": 1}, crop_size=32),
    # about an hour per experiment on a 2-core CPU
    "small": Scale(size=64, steps=2000, test=200, pool_labelled=100, pool_unlabelled=1000, seeds=3),
    # the whole grid at the default training scale (TrainConfig defaults: 96 px, 3000 steps)
    "full": Scale(size=96, steps=3000, test=200, pool_labelled=100, pool_unlabelled=3000, seeds=3),
}

#: Grid axes per experiment and scale. ``claim`` selects the points that get ``Scale.seeds`` seeds.
GRIDS: dict[str, dict[str, dict[str, list]]] = {
    "label-efficiency": {
        "toy": {"labelled": [3], "unlabelled": [0, 4]},
        "small": {"labelled": [3, 10, 30, 100], "unlabelled": [0, 300, 1000]},
        "full": {"labelled": [3, 10, 30, 100], "unlabelled": [0, 300, 3000]},
    },
    "domain-shift": {
        "toy": {"modes": ["start", "full"], "labelled": [3], "unlabelled": [4]},
        "small": {"modes": ["start", "full"], "labelled": [3, 10, 30], "unlabelled": [0, 1000]},
        "full": {"modes": ["start", "full"], "labelled": [3, 10, 30, 100], "unlabelled": [0, 3000]},
    },
    "category": {
        "toy": {"instances": [1, 2], "labelled": [3], "unlabelled": [4]},
        "small": {"instances": [1, 2, 3, 6, 8, 12], "labelled": [30], "unlabelled": [1000]},
        "full": {"instances": [1, 2, 3, 6, 8, 12], "labelled": [30], "unlabelled": [3000]},
    },
    "alpha": {
        "toy": {"alphas": [0.1, 1.0], "labelled": [3], "unlabelled": [4]},
        "small": {"alphas": [0.1, 0.25, 0.5, 1.0], "labelled": [3, 30], "unlabelled": [1000]},
        "full": {"alphas": [0.1, 0.25, 0.5, 1.0], "labelled": [3, 10, 100], "unlabelled": [3000]},
    },
}

#: One line per experiment for --help and the printed plan.
DESCRIPTIONS = {
    "label-efficiency": "4.1 box: labelled x unlabelled frames; unlabelled 0 is the labels-only baseline",
    "domain-shift": "4.2 distractors: labels from the first distractor set (start) or all (full)",
    "category": "4.3 category: train on 1-12 instances, test on 4 held-out ones",
    "alpha": "appendix C: weight alpha of the self-supervised term",
}
EXPERIMENTS = tuple(GRIDS)

#: With two passes the pool is rendered this many times larger than the coarse pass's input (384 px for 96:
#: the crops are cut from images of about the paper's 400 px).
TWO_PASS_RENDER_FACTOR = 4

# Rough cost model for the printed estimate: CPU seconds per training step on one thread, a + b * pixels,
# fitted to timed 30-step runs at 64 and 96 px on this project's 2-core machine; and images rendered per
# second with 2 rendering processes (4480 images at 64 px in 21 s, measured under load).
_STEP_COST = {False: (0.034, 1.35e-5), True: (0.105, 1.72e-5)}
RENDER_IMAGES_PER_S = 150.0


def step_seconds(size: int, unsup: bool) -> float:
    """Estimated CPU seconds per training step (one thread) at ``size`` x ``size`` px."""
    a, b = _STEP_COST[bool(unsup)]
    return a + b * size * size


# ------------------------------------------------------------------------------------------------------------
# What to run


@dataclass(frozen=True)
class PoolSpec:
    """One rendered dataset shared by the runs that pick their frames from it."""

    scene: str
    size: int
    labelled: int
    unlabelled: int
    test: int
    seed: int = 0
    mode: str = "full"
    train_instances: int = 12

    @property
    def name(self) -> str:
        parts = [self.scene]
        if self.scene == "distractors":
            parts.append(self.mode)
        if self.scene == "category":
            parts.append(f"i{self.train_instances}")
        parts += [f"{self.size}px", f"L{self.labelled}", f"U{self.unlabelled}", f"T{self.test}",
                  f"seed{self.seed}"]
        return "-".join(parts)

    def simulate_config(self):
        from s3k.sim.generate import SimulateConfig

        return SimulateConfig(scene=self.scene, size=self.size, labelled=self.labelled,
                              unlabelled=self.unlabelled, test=self.test, seed=self.seed, mode=self.mode,
                              train_instances=self.train_instances)

    def images(self) -> int:
        return 4 * (self.labelled + self.unlabelled + self.test)


@dataclass
class RunSpec:
    """One point of a sweep with one seed.

    Attributes:
        experiment: experiment name.
        name: run folder name (unique within the experiment).
        params: the grid coordinates (labelled, unlabelled, seed, method, and mode / instances / alpha).
        pool: the dataset the frames come from.
        labelled, unlabelled: frames picked from the pool for training (all test frames are used).
        seed: run seed (training seed and choice of labelled frames).
        cfg: training configuration (of both passes when ``two_pass`` is set).
        eval_train: also evaluate on training-instance frames (category).
        label_choice: how the labelled frames are chosen from the pool
            (:data:`LABEL_CHOICES`).
        two_pass: None for one pass on the whole image; else the two-pass fields of the configuration
            (``coarse_size``, ``coarse_steps``, ``coarse_rotation``, ``crop_size``): a coarse pass on the
            whole image resized, a refining pass on crops around its estimate (:meth:`train_config`).
    """

    experiment: str
    name: str
    params: dict[str, Any]
    pool: PoolSpec
    labelled: int
    unlabelled: int
    seed: int
    cfg: TrainConfig
    eval_train: bool = False
    two_pass: dict[str, Any] | None = None
    label_choice: str = "random"

    def train_config(self) -> TrainConfig:
        """The configuration the run trains with: ``cfg`` with ``two_pass`` and its fields where set."""
        return self.cfg if self.two_pass is None else self.cfg.replace(two_pass=True, **self.two_pass)

    def estimated_cpu_s(self) -> float:
        c = self.cfg

        def one_pass(steps: int, size: int) -> float:
            warm = min(steps, c.self_supervision.warmup_steps) if c.self_supervision.unsup else steps
            return warm * step_seconds(size, False) + (steps - warm) * step_seconds(size, True)

        if self.two_pass is None:
            return one_pass(c.schedule.steps, self.pool.size)
        return (one_pass(self.two_pass["coarse_steps"], self.two_pass["coarse_size"])
                + one_pass(c.schedule.steps, self.two_pass["crop_size"]))


@dataclass
class Options:
    """Resolved options of a sweep (the command line's ``s3k experiment`` options).

    Attributes:
        experiment: one of :data:`EXPERIMENTS`.
        out: the workspace folder (``data/`` and one folder per experiment).
        scale: one of :data:`SCALES`.
        seeds: seeds at the points carrying a claim (None: the scale's); ``seeds_other`` at the others.
        steps, size, test: training steps, image size, test frames (None: the scale's).
        data_seed: seed of the rendered datasets.
        labelled, unlabelled, instances, alphas, modes: grid axes replacing the scale's (None: keep).
        train_overrides: TrainConfig fields for every run (``--set FIELD=VALUE``; values may be text).
        two_pass: train every run coarse-to-fine (``s3k train --two-pass``): the pools are rendered at
            ``render`` px (None: :data:`TWO_PASS_RENDER_FACTOR` x ``size``), the coarse pass sees them at
            ``size`` px for ``coarse_steps`` (None: ``steps``) with rotations up to ``coarse_rotation``
            degrees (None: the configuration's), the refining pass ``crop_size`` px crops (None: the
            scale's).
        label_choice: how runs choose their labelled frames from the pool: "random" (stratified),
            "coverage" or "representative" (the labelling app's pose orders over the pool's true poses).
        command: the command line of the sweep, recorded in each run's result.
        device, threads, progress: how runs execute (they do not change a run's result).
        workers: rendering processes (None: one per CPU).
    """

    experiment: str
    out: Path
    scale: str = "toy"
    seeds: int | None = None
    seeds_other: int = 1
    steps: int | None = None
    size: int | None = None
    test: int | None = None
    data_seed: int = 0
    labelled: list[int] | None = None
    unlabelled: list[int] | None = None
    instances: list[int] | None = None
    alphas: list[float] | None = None
    modes: list[str] | None = None
    train_overrides: dict[str, Any] = field(default_factory=dict)
    two_pass: bool = False
    render: int | None = None
    coarse_steps: int | None = None
    coarse_rotation: float | None = None
    crop_size: int | None = None
    label_choice: str = "random"
    command: str | None = None
    device: Device = "cpu"
    threads: int = 0
    workers: int | None = None
    progress: bool = True


def train_config(opts: Options, scale: Scale, steps: int, seed: int, unsup: bool,
                 alpha: float) -> TrainConfig:
    """The training configuration of one run; every run's config is built here and nowhere else.

    Precedence: the default schedule scaled to ``steps`` < the scale's fields < ``opts.train_overrides`` <
    the run's own ``seed``, ``unsup`` and ``alpha`` (grid coordinates are never overridden).

    Raises:
        UserError: an override names an unknown field or gives a value out of range.
    """
    # warm-up and ramp keep the default schedule's proportions (750 + 750 of 3000 steps)
    base = TrainConfig()
    s, every = base.self_supervision, base.monitoring.checkpoint_every
    frac = s.warmup_steps / base.schedule.steps, s.ramp_steps / base.schedule.steps
    values: dict[str, Any] = dict(steps=steps, warmup_steps=int(steps * frac[0]),
                                  ramp_steps=int(steps * frac[1]),
                                  checkpoint_every=max(1, min(every, steps // 6)),
                                  device=opts.device, threads=opts.threads, progress=opts.progress)
    values.update(scale.train)
    values.update(opts.train_overrides)
    values.update(seed=seed, unsup=unsup, alpha=alpha)
    try:
        cfg = TrainConfig.from_flat(where="--set", **values)
        cfg.validate()
    except UserError:
        raise
    except ValueError as exc:
        raise UserError(str(exc), hint="change the --set values") from exc
    return cfg


def _seed_count(opts: Options, scale: Scale, claim: bool) -> int:
    n = opts.seeds if opts.seeds is not None else scale.seeds
    return max(1, n if claim else min(n, opts.seeds_other))


def plan(opts: Options) -> list[RunSpec]:
    """Every run of ``opts.experiment`` at ``opts.scale`` (with overrides), in the order they run.

    Raises:
        UserError: an unknown experiment or scale, or a grid value out of range (names the option).
    """
    if opts.experiment not in GRIDS:
        raise UserError(f"experiment: unknown {opts.experiment!r}",
                        hint=f"choose from {', '.join(EXPERIMENTS)}")
    if opts.scale not in SCALES:
        raise UserError(f"--scale: unknown {opts.scale!r}", hint=f"choose from {', '.join(SCALES)}")
    scale = SCALES[opts.scale]
    grid = {k: list(v) for k, v in GRIDS[opts.experiment][opts.scale].items()}
    for key in ("labelled", "unlabelled", "instances", "alphas", "modes"):
        value = getattr(opts, key)
        if value is not None:
            if key not in grid:
                raise UserError(f"--{key} does not apply to experiment {opts.experiment!r}")
            grid[key] = list(value)
    size = opts.size or scale.size
    steps = opts.steps or scale.steps
    test = opts.test or scale.test
    if opts.label_choice not in LABEL_CHOICES:
        raise UserError(f"--label-choice: unknown {opts.label_choice!r}",
                        hint=f"choose from {', '.join(LABEL_CHOICES)}")
    two_pass = None
    if opts.two_pass:
        two_pass = {"coarse_size": size, "coarse_steps": opts.coarse_steps or steps,
                    "coarse_rotation": opts.coarse_rotation, "crop_size": opts.crop_size or scale.crop_size}
        size = opts.render or TWO_PASS_RENDER_FACTOR * size  # the pools' size: the crops are cut from them
    elif any(v is not None for v in (opts.render, opts.coarse_steps, opts.coarse_rotation, opts.crop_size)):
        raise UserError("--render, --coarse-steps, --coarse-rotation and --crop-size apply only to two-pass "
                        "runs", hint="add --two-pass, or leave them out")
    if any(n <= 0 for n in grid["labelled"]) or any(n < 0 for n in grid["unlabelled"]):
        raise UserError(f"--labelled must be > 0 and --unlabelled >= 0, got {grid['labelled']}, "
                        f"{grid['unlabelled']}")
    pool_l = max([scale.pool_labelled, *grid["labelled"]])
    pool_u = max([scale.pool_unlabelled, *grid["unlabelled"]])
    exp = opts.experiment
    runs: list[RunSpec] = []

    def add(name: str, params: dict, pool: PoolSpec, L: int, U: int, claim: bool, alpha: float = 0.5,
            eval_train: bool = False) -> None:
        for s in range(_seed_count(opts, scale, claim)):
            cfg = train_config(opts, scale, steps, s, U > 0, alpha)
            if two_pass is not None and cfg.model.image_size:
                raise UserError("--set image_size does not apply to two-pass runs",
                                hint="set the coarse pass's size with --size and the crops' with --crop-size")
            p = dict(params, labelled=L, unlabelled=U, seed=s, method="s3k" if U > 0 else "no_unsup")
            if opts.label_choice != "random":
                p["labels"] = opts.label_choice
            runs.append(RunSpec(exp, f"{name}-s{s}", p, pool, L, U, s, cfg, eval_train, two_pass,
                                opts.label_choice))

    if exp == "label-efficiency":
        pool = PoolSpec(EXPERIMENT_SCENES[exp], size, pool_l, pool_u, test, opts.data_seed)
        for L in grid["labelled"]:
            for U in grid["unlabelled"]:
                add(f"L{L}-U{U}", {}, pool, L, U, claim=L in (3, 10))
    elif exp == "domain-shift":
        for mode in grid["modes"]:
            if mode not in ("start", "full"):
                raise UserError(f"--modes: each must be 'start' or 'full', got {mode!r}")
            pool = PoolSpec(EXPERIMENT_SCENES[exp], size, pool_l, pool_u, test, opts.data_seed, mode=mode)
            for L in grid["labelled"]:
                for U in grid["unlabelled"]:
                    add(f"{mode}-L{L}-U{U}", {"mode": mode}, pool, L, U, claim=L in (3, 10))
    elif exp == "category":
        L, U = max(grid["labelled"]), max(grid["unlabelled"])
        for n in grid["instances"]:
            if not 1 <= n <= 12:
                raise UserError(f"--instances: each must be in [1, 12], got {n}")
            pool = PoolSpec(EXPERIMENT_SCENES[exp], size, L, U, test, opts.data_seed, train_instances=n)
            add(f"inst{n}-L{L}-U{U}", {"instances": n}, pool, L, U, claim=n in (1, 12), eval_train=True)
    elif exp == "alpha":
        pool = PoolSpec(EXPERIMENT_SCENES[exp], size, pool_l, pool_u, test, opts.data_seed)
        U = max(grid["unlabelled"])
        if U <= 0:
            raise UserError("--unlabelled: the alpha experiment needs unlabelled frames")
        for L in grid["labelled"]:
            for a in grid["alphas"]:
                if a <= 0:
                    raise UserError(f"--alphas: each must be > 0, got {a}")
                add(f"alpha{a:g}-L{L}-U{U}", {"alpha": float(a)}, pool, L, U, claim=L in (3, 10), alpha=a)
    return runs
