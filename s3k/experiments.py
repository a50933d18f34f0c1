"""``s3k experiment NAME --out DIR``: the paper's experiments as resumable sweeps, with a summary and plots.

Experiments (section numbers of Vecerik et al., CoRL 2020):

- ``label-efficiency`` (4.1): box scene; labelled x unlabelled frame counts; unlabelled 0 is the labels-only
  baseline (``--no-unsup``). Plots: error per labelled count (one curve per unlabelled count) and error
  against the total number of frames coloured by the labelled share.
- ``domain-shift`` (4.2): distractors scene, labels from the first distractor set only ("start") or spread
  over the whole timeline ("full"), over labelled and unlabelled counts; test on distractor sets never seen.
- ``category`` (4.3): category scene, trained on 1-12 instances, evaluated on the training instances (frames
  never labelled) and on the 4 held-out ones; compared with the paper's table (400 px).
- ``alpha`` (appendix C): weight of the self-supervised term at a few labelled counts.

Layout of ``DIR`` (one DIR can hold every experiment of one scale; they share the rendered data)::

    DIR/data/<pool>/                 a rendered dataset per (scene, mode, instances, size, frame counts, seed)
    DIR/data/views/<pool>/<view>/    a run's frames of a pool: CSV tables filtered, images linked, not copied
    DIR/<experiment>/runs/<run>/     the training run folder (s3k.run) and result.json once finished
    DIR/<experiment>/summary.json    per grid point: mean, std and values over seeds; findings
    DIR/<experiment>/*.png, README.md

Resuming: a run with a ``result.json`` is never redone; a run killed during training continues from its last
checkpoint (``train(..., resume=True)``); a dataset is rendered into ``NAME.tmp`` and renamed when complete.
Several invocations on one DIR may run at the same time (e.g. one per core with ``--threads 1``): a run being
trained by a live process is skipped (lock file ``run.lock`` holding the pid), a pool being rendered is
waited for.

Seeds: run seed ``s`` trains with ``TrainConfig.seed = s`` on its own random choice of labelled frames from
the pool (nested: the first 3 of a seed's 10); the unlabelled and test frames do not depend on the seed, so
the runs of one grid point differ in the labelled frames and the initialization.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from s3k.config import TrainConfig, config_from_dict

#: The paper's image size (pixels) and training length (batches): errors are also shown at this scale.
PAPER_SIZE = 400
PAPER_STEPS = 150_000

#: Paper, sec. 4.3 table: test rms error (pixels at 400 px) on the held-out instances per training instances.
PAPER_CATEGORY_TEST_PX = {1: 26.99, 2: 14.65, 3: 16.22, 6: 15.05, 8: 11.75, 12: 10.77}

METRICS = ("rms_px", "rms_px_reproj", "median_mm", "rms_mm")

#: Config fields that do not change a run's result: a finished run is kept when only these differ.
_NEUTRAL_FIELDS = ("progress", "device", "threads", "preload_mb", "val_every", "val_frames", "log_every",
                   "checkpoint_every")

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
    """

    size: int
    steps: int
    test: int
    pool_labelled: int
    pool_unlabelled: int
    seeds: int
    train: dict[str, Any] = field(default_factory=dict)


SCALES: dict[str, Scale] = {
    # seconds per experiment; what the tests run
    "toy": Scale(size=32, steps=2, test=2, pool_labelled=3, pool_unlabelled=4, seeds=1,
                 train={"channels": (8, 16, 16), "res_blocks": 1, "batch_labelled": 2, "batch_unlabelled": 2,
                        "val_every": 0, "checkpoint_every": 1}),
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

# Rough cost model for the printed estimate: CPU seconds per training step on one thread, a + b * pixels,
# fitted to timed 30-step runs at 64 and 96 px on this project's 2-core machine; and images rendered per
# second with 2 rendering processes (4480 images at 64 px in 21 s, measured under load).
_STEP_COST = {False: (0.034, 1.35e-5), True: (0.105, 1.72e-5)}
_RENDER_IMAGES_PER_S = 150.0


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
        cfg: training configuration.
        eval_train: also evaluate on training-instance frames (category).
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

    def estimated_cpu_s(self) -> float:
        c = self.cfg
        warm = min(c.steps, c.warmup_steps) if c.unsup else c.steps
        return warm * step_seconds(self.pool.size, False) + (c.steps - warm) * step_seconds(self.pool.size,
                                                                                             True)


@dataclass
class Options:
    """Resolved command-line options of a sweep (see :func:`configure_parser`)."""

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
    command: str | None = None  # the command line of the sweep, recorded in each run's result
    device: str = "cpu"
    threads: int = 0
    workers: int | None = None
    progress: bool = True


def _train_config(opts: Options, scale: Scale, steps: int, seed: int, unsup: bool,
                  alpha: float) -> TrainConfig:
    # warm-up and ramp keep the default schedule's proportions (750 + 750 of 3000 steps)
    base = TrainConfig()
    frac = base.warmup_steps / base.steps, base.ramp_steps / base.steps
    values = dict(steps=steps, warmup_steps=int(steps * frac[0]), ramp_steps=int(steps * frac[1]),
                  checkpoint_every=max(1, min(base.checkpoint_every, steps // 6)), seed=seed, unsup=unsup,
                  alpha=alpha, device=opts.device, threads=opts.threads, progress=opts.progress)
    values.update(scale.train)
    values.update(opts.train_overrides)
    values.update(seed=seed, unsup=unsup, alpha=alpha)
    cfg = config_from_dict(TrainConfig, values, where="experiment")
    cfg.validate()
    return cfg


def _seed_count(opts: Options, scale: Scale, claim: bool) -> int:
    n = opts.seeds if opts.seeds is not None else scale.seeds
    return max(1, n if claim else min(n, opts.seeds_other))


def plan(opts: Options) -> list[RunSpec]:
    """Every run of ``opts.experiment`` at ``opts.scale`` (with overrides), in the order they run."""
    if opts.experiment not in GRIDS:
        raise ValueError(f"experiment: unknown {opts.experiment!r}; choose from {', '.join(EXPERIMENTS)}")
    if opts.scale not in SCALES:
        raise ValueError(f"--scale: unknown {opts.scale!r}; choose from {', '.join(SCALES)}")
    scale = SCALES[opts.scale]
    grid = {k: list(v) for k, v in GRIDS[opts.experiment][opts.scale].items()}
    for key in ("labelled", "unlabelled", "instances", "alphas", "modes"):
        value = getattr(opts, key)
        if value is not None:
            if key not in grid:
                raise ValueError(f"--{key} does not apply to experiment {opts.experiment!r}")
            grid[key] = list(value)
    size = opts.size or scale.size
    steps = opts.steps or scale.steps
    test = opts.test or scale.test
    if any(n <= 0 for n in grid["labelled"]) or any(n < 0 for n in grid["unlabelled"]):
        raise ValueError(f"--labelled must be > 0 and --unlabelled >= 0, got {grid['labelled']}, "
                         f"{grid['unlabelled']}")
    pool_l = max([scale.pool_labelled, *grid["labelled"]])
    pool_u = max([scale.pool_unlabelled, *grid["unlabelled"]])
    exp = opts.experiment
    runs: list[RunSpec] = []

    def add(name: str, params: dict, pool: PoolSpec, L: int, U: int, claim: bool, alpha: float = 0.5,
            eval_train: bool = False) -> None:
        for s in range(_seed_count(opts, scale, claim)):
            cfg = _train_config(opts, scale, steps, s, U > 0, alpha)
            p = dict(params, labelled=L, unlabelled=U, seed=s, method="s3k" if U > 0 else "no_unsup")
            runs.append(RunSpec(exp, f"{name}-s{s}", p, pool, L, U, s, cfg, eval_train))

    if exp == "label-efficiency":
        pool = PoolSpec("box", size, pool_l, pool_u, test, opts.data_seed)
        for L in grid["labelled"]:
            for U in grid["unlabelled"]:
                add(f"L{L}-U{U}", {}, pool, L, U, claim=L in (3, 10))
    elif exp == "domain-shift":
        for mode in grid["modes"]:
            if mode not in ("start", "full"):
                raise ValueError(f"--modes: each must be 'start' or 'full', got {mode!r}")
            pool = PoolSpec("distractors", size, pool_l, pool_u, test, opts.data_seed, mode=mode)
            for L in grid["labelled"]:
                for U in grid["unlabelled"]:
                    add(f"{mode}-L{L}-U{U}", {"mode": mode}, pool, L, U, claim=L in (3, 10))
    elif exp == "category":
        L, U = max(grid["labelled"]), max(grid["unlabelled"])
        for n in grid["instances"]:
            if not 1 <= n <= 12:
                raise ValueError(f"--instances: each must be in [1, 12], got {n}")
            pool = PoolSpec("category", size, L, U, test, opts.data_seed, train_instances=n)
            add(f"inst{n}-L{L}-U{U}", {"instances": n}, pool, L, U, claim=n in (1, 12), eval_train=True)
    elif exp == "alpha":
        pool = PoolSpec("box", size, pool_l, pool_u, test, opts.data_seed)
        U = max(grid["unlabelled"])
        if U <= 0:
            raise ValueError("--unlabelled: the alpha experiment needs unlabelled frames")
        for L in grid["labelled"]:
            for a in grid["alphas"]:
                if a <= 0:
                    raise ValueError(f"--alphas: each must be > 0, got {a}")
                add(f"alpha{a:g}-L{L}-U{U}", {"alpha": float(a)}, pool, L, U, claim=L in (3, 10), alpha=a)
    return runs


# ------------------------------------------------------------------------------------------------------------
# Locks, atomic files


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def _claim(path: Path) -> Iterator[bool]:
    """Take the lock file ``path`` (pid and host inside); yields False when a live process holds it."""
    me = f"{os.getpid()} {socket.gethostname()}"
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid_text, host = (path.read_text().split() + ["", ""])[:2]
                pid = int(pid_text)
                age = time.time() - path.stat().st_mtime
            except (OSError, ValueError):
                pid, host, age = -1, "", 0.0
            dead = host == socket.gethostname() and pid > 0 and not _pid_alive(pid)
            unreadable = pid < 0 and age > 30.0  # a lock is written right after it is created
            if dead or unreadable:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()  # stale: its process is gone
                continue
            yield False
            return
        with os.fdopen(fd, "w") as fh:
            fh.write(me)
        try:
            yield True
        finally:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        return
    yield False


def _write_json(obj: Any, path: Path) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
    os.replace(tmp, path)


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.integer, np.floating)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serializable: {type(x).__name__}")


# ------------------------------------------------------------------------------------------------------------
# Datasets: pools and views


def ensure_pool(data_dir: Path, pool: PoolSpec, workers: int | None = None, progress: bool = True,
                log: Callable[[str], None] = print) -> tuple[Path, bool]:
    """Render ``pool`` into ``data_dir/pool.name`` unless it is there; returns (path, rendered now)."""
    from s3k.sim.generate import simulate

    path = data_dir / pool.name
    data_dir.mkdir(parents=True, exist_ok=True)
    while not (path / "s3k.json").is_file():
        with _claim(data_dir / f"{pool.name}.lock") as mine:
            if not mine:
                time.sleep(2.0)  # another process renders it
                continue
            if (path / "s3k.json").is_file():
                break
            tmp = data_dir / f"{pool.name}.tmp"
            log(f"rendering {pool.name} ({pool.images()} images)")
            t0 = time.perf_counter()
            simulate(pool.simulate_config(), tmp, workers=workers, progress=progress, overwrite=True)
            os.replace(tmp, path)
            log(f"rendered {pool.name} in {time.perf_counter() - t0:.0f} s")
            return path, True
    return path, False


def stratified_pick(ids: np.ndarray, groups: np.ndarray | None, n: int,
                    rng: np.random.Generator) -> np.ndarray:
    """``n`` of ``ids`` drawn round-robin over ``groups`` (each group shuffled by ``rng``), sorted.

    The picks of a larger ``n`` contain those of a smaller one (same ``rng`` state), so labelled sets nest.

    Args:
        ids: (N,) frame ids.
        groups: (N,) group label per frame (distractor segment, object instance) or None (one group).
        n: how many to pick (at most N).
        rng: random generator.

    Returns:
        (n,) sorted frame ids.
    """
    ids = np.asarray(ids)
    if n > len(ids):
        raise ValueError(f"cannot pick {n} frames from {len(ids)}")
    groups = np.zeros(len(ids), int) if groups is None else np.asarray(groups)
    queues = []
    for g in sorted(set(groups.tolist()), key=str):
        members = ids[groups == g]
        queues.append(list(members[rng.permutation(len(members))]))
    order: list[int] = []
    while len(order) < n:
        for q in queues:
            if q and len(order) < n:
                order.append(int(q.pop(0)))
    return np.sort(np.asarray(order, dtype=np.int64))


def _group_column(root: Path) -> str | None:
    header = (root / "frames.csv").read_text().split("\n", 1)[0].split(",")
    for name in ("segment", "instance"):
        if name in header:
            return name
    return None


def _read_frames(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(frame ids, splits, group labels or None) of a dataset's frames.csv."""
    col = _group_column(root)
    ids, splits, groups = [], [], []
    with open(root / "frames.csv", newline="") as fh:
        rows = (r for r in csv.DictReader(line for line in fh if not line.startswith("#")))
        for r in rows:
            ids.append(int(r["frame"]))
            splits.append(r["split"].strip())
            groups.append(r[col].strip() if col else "")
    return np.asarray(ids, np.int64), np.asarray(splits), (np.asarray(groups) if col else None)


def select_frames(pool_dir: Path, labelled: int, unlabelled: int, seed: int,
                  data_seed: int = 0) -> dict[str, np.ndarray]:
    """The frames of one run: ``labelled`` chosen by run ``seed``, ``unlabelled`` fixed, every test frame.

    Both choices are stratified over distractor segments / object instances, so "full" mode keeps labels
    spread over the timeline and every training instance keeps its share.
    """
    ids, splits, groups = _read_frames(pool_dir)
    out = {}
    for split, n, rng in (("labelled", labelled, np.random.default_rng([data_seed, seed, 1])),
                          ("unlabelled", unlabelled, np.random.default_rng([data_seed, 2]))):
        sel = splits == split
        if n > sel.sum():
            raise ValueError(f"{pool_dir}: run needs {n} {split} frames, the dataset has {int(sel.sum())}")
        out[split] = stratified_pick(ids[sel], None if groups is None else groups[sel], n, rng)
    out["test"] = ids[splits == "test"]
    return out


def make_view(pool_dir: Path, view_dir: Path, frames: dict[str, np.ndarray],
              note: dict | None = None) -> Path:
    """A dataset folder holding ``frames`` (split -> ids) of ``pool_dir``, with the splits given.

    The CSV tables are filtered to those frames and the image folder is a symbolic link to the pool's, so a
    view costs a few kilobytes. Built in a temporary folder and renamed, so it is complete or absent.
    """
    if (view_dir / "s3k.json").is_file():
        return view_dir
    split_of = {int(f): split for split, ids in frames.items() for f in np.asarray(ids).tolist()}
    view_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = view_dir.with_name(f"{view_dir.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    meta = json.loads((pool_dir / "s3k.json").read_text())
    images = meta.get("images") or {}
    if images.get("type", "png") != "png":
        raise ValueError(f"{pool_dir}: views need PNG images, the dataset has {images.get('type')!r}")
    top = str(images.get("pattern", "images/{camera}/{frame:06d}.png")).split("/", 1)[0]
    os.symlink(os.path.relpath(pool_dir / top, view_dir), tmp / top, target_is_directory=True)
    meta["source"] = {"view_of": os.path.relpath(pool_dir, view_dir),
                      "pool_source": meta.get("source"), **(note or {})}
    (tmp / "s3k.json").write_text(json.dumps(meta, indent=2) + "\n")
    for table in sorted(pool_dir.glob("*.csv")):
        with open(table, newline="") as fh:
            lines = [line for line in fh if not line.startswith("#")]
        reader = csv.reader(lines)
        header = next(reader)
        if "frame" not in header:
            shutil.copyfile(table, tmp / table.name)
            continue
        fcol = header.index("frame")
        scol = header.index("split") if table.name == "frames.csv" else None
        with open(tmp / table.name, "w", newline="") as out:
            writer = csv.writer(out, lineterminator="\n")
            writer.writerow(header)
            for row in reader:
                if not row:
                    continue
                f = int(row[fcol])
                if f in split_of:
                    if scol is not None:
                        row[scol] = split_of[f]
                    writer.writerow(row)
    try:
        os.rename(tmp, view_dir)
    except OSError:  # another process made the same view first
        shutil.rmtree(tmp, ignore_errors=True)
    return view_dir


def _drop_cache(dataset_dir: Path) -> None:
    """Remove a view's decoded-image cache (the loader's ``.cache``); it is rebuilt on demand."""
    shutil.rmtree(dataset_dir / ".cache", ignore_errors=True)


# ------------------------------------------------------------------------------------------------------------
# Running


def _differences(saved: dict[str, Any], cfg: TrainConfig) -> list[str]:
    now = cfg.to_dict()
    return [f"{k}: {saved.get(k)!r} there, {v!r} now" for k, v in now.items()
            if k not in _NEUTRAL_FIELDS and saved.get(k) != v]


def run_one(spec: RunSpec, exp_dir: Path, data_dir: Path, opts: Options,
            log: Callable[[str], None] = print) -> dict[str, Any] | None:
    """Train and evaluate one run unless finished; returns its result (None: another process has it).

    Raises:
        ValueError: the run folder holds a run made with other settings (names the fields).
    """
    from s3k.evaluate import evaluate_run
    from s3k.train import train

    run_dir = exp_dir / "runs" / spec.name
    result_path = run_dir / RESULT_FILE
    if result_path.is_file():
        result = json.loads(result_path.read_text())
        diff = _differences(result["config"], spec.cfg)
        if diff:
            raise ValueError(f"{result_path}: finished with other settings ({'; '.join(diff)}); use another "
                             "--out")
        return result
    run_dir.mkdir(parents=True, exist_ok=True)
    with _claim(run_dir / "run.lock") as mine:
        if not mine:
            log(f"{spec.name}: being trained by another process; skipped")
            return None
        if result_path.is_file():  # finished by another process meanwhile
            return json.loads(result_path.read_text())
        if (run_dir / "config.json").is_file():
            saved = json.loads((run_dir / "config.json").read_text())["config"]
            diff = _differences(saved, spec.cfg)
            if diff:
                raise ValueError(f"{run_dir}: a run with other settings is there ({'; '.join(diff)}); use "
                                 "another --out")
        t0 = time.perf_counter()
        pool_dir, _ = ensure_pool(data_dir, spec.pool, opts.workers, opts.progress, log)
        frames = select_frames(pool_dir, spec.labelled, spec.unlabelled, spec.seed, spec.pool.seed)
        view_name = f"L{spec.labelled}-s{spec.seed}-U{spec.unlabelled}"
        view = make_view(pool_dir, data_dir / "views" / spec.pool.name / view_name,
                         {k: v for k, v in frames.items() if len(v)},
                         {"labelled": spec.labelled, "unlabelled": spec.unlabelled, "seed": spec.seed})
        t_data = time.perf_counter() - t0
        start_step = 0
        with contextlib.suppress(Exception):
            import torch

            start_step = int(torch.load(run_dir / "checkpoint.pt", map_location="cpu",
                                        weights_only=False)["step"])
        log(f"{spec.name}: training {spec.cfg.steps} steps "
            f"({'S3K' if spec.cfg.unsup else 'labels only'}, {spec.labelled} labelled, {spec.unlabelled} "
            f"unlabelled, seed {spec.seed})" + (f", resuming at step {start_step}" if start_step else ""))
        t1 = time.perf_counter()
        trained = train(view, run_dir, spec.cfg, resume=True)
        t_train = time.perf_counter() - t1
        t2 = time.perf_counter()
        metrics = {"test": evaluate_run(run_dir, view, "test", device=opts.device)}
        if spec.eval_train:
            eval_ids = select_frames(pool_dir, 0, min(spec.pool.unlabelled, spec.pool.test), 0,
                                     spec.pool.seed)["unlabelled"]
            train_view = make_view(pool_dir, data_dir / "views" / spec.pool.name / "train-instances-eval",
                                   {"test": eval_ids}, {"purpose": "evaluation on training instances"})
            metrics["train"] = evaluate_run(run_dir, train_view, "test", device=opts.device)
            _drop_cache(train_view)
        t_eval = time.perf_counter() - t2
        _drop_cache(view)
        size = metrics["test"]["image_size"][0]
        result = {
            "experiment": spec.experiment, "run": spec.name, "params": spec.params,
            "status": trained.status, "steps": trained.step, "image_size": metrics["test"]["image_size"],
            "px_to_paper": PAPER_SIZE / size, "scale": opts.scale,
            "data": {"pool": spec.pool.name, "pool_spec": dataclasses.asdict(spec.pool),
                     "view": os.path.relpath(view, exp_dir),
                     "frames": {k: len(v) for k, v in frames.items()}},
            "config": spec.cfg.to_dict(), "metrics": metrics,
            "wall_time_s": {"data": t_data, "train": t_train, "evaluate": t_eval,
                            "total": time.perf_counter() - t0},
            "train_timing": trained.timing, "resumed_from_step": start_step,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "host": socket.gethostname(),
            "command": opts.command, "code_revision": source_revision(),
        }
        _write_json(result, result_path)
        m = metrics["test"]
        log(f"{spec.name}: rms_px {_fmt(m['rms_px'])} ({_fmt(_scaled(m['rms_px'], size))} at {PAPER_SIZE} "
            f"px), "
            f"median_mm {_fmt(m['median_mm'])}, {result['wall_time_s']['total']:.0f} s")
        return result


def _scaled(v: float | None, size: int) -> float | None:
    return None if v is None else v * PAPER_SIZE / size


def _fmt(v: Any, digits: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def describe_plan(runs: Sequence[RunSpec], exp_dir: Path, data_dir: Path, scale: str) -> str:
    """What a sweep will do: runs, datasets to render, estimated CPU time."""
    if not runs:
        return f"scale {scale}: no runs"
    pools = {r.pool.name: r.pool for r in runs}
    done = sum((exp_dir / "runs" / r.name / RESULT_FILE).is_file() for r in runs)
    todo = [r for r in runs if not (exp_dir / "runs" / r.name / RESULT_FILE).is_file()]
    missing = [p for n, p in pools.items() if not (data_dir / n / "s3k.json").is_file()]
    cpu = sum(r.estimated_cpu_s() for r in todo) + sum(p.images() for p in missing) / _RENDER_IMAGES_PER_S
    n_base = sum(not r.cfg.unsup for r in runs)
    sizes = sorted({r.pool.size for r in runs})
    steps = sorted({r.cfg.steps for r in runs})
    return (f"{runs[0].experiment} ({DESCRIPTIONS[runs[0].experiment]}), scale {scale}: {len(runs)} runs "
            f"({n_base} labels-only, {len(runs) - n_base} S3K; {done} already finished), "
            f"{len(pools)} dataset(s) ({len(missing)} to render, "
            f"{sum(p.images() for p in missing)} images), {'/'.join(map(str, sizes))} px, "
            f"{'/'.join(map(str, steps))} steps; estimated {cpu / 3600:.2f} CPU-hours left "
            f"(one process, one thread per run; about half the wall time with two invocations in parallel)")


def run_experiment(opts: Options, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run every missing run of a sweep, then summarize. Returns ``{"trained", "skipped", "failed",
    "summary"}`` (run names trained now, already finished or held by another process, failed)."""
    runs = plan(opts)
    exp_dir = opts.out / opts.experiment
    data_dir = opts.out / "data"
    exp_dir.mkdir(parents=True, exist_ok=True)
    log(describe_plan(runs, exp_dir, data_dir, opts.scale))
    trained: list[str] = []
    skipped: list[str] = []
    failed: list[str] = []
    for i, spec in enumerate(runs):
        finished = (exp_dir / "runs" / spec.name / RESULT_FILE).is_file()
        if finished:
            run_one(spec, exp_dir, data_dir, opts, log)  # checks the settings match
            skipped.append(spec.name)
            continue
        log(f"[{i + 1}/{len(runs)}] {spec.name}")
        try:
            result = run_one(spec, exp_dir, data_dir, opts, log)
        except KeyboardInterrupt:
            raise
        except ValueError as exc:
            if "other settings" in str(exc):
                raise
            log(f"{spec.name}: FAILED: {exc}")
            failed.append(spec.name)
            continue
        except Exception as exc:  # one broken run must not stop the sweep
            log(f"{spec.name}: FAILED: {exc}\n{traceback.format_exc()}")
            failed.append(spec.name)
            continue
        (trained if result is not None else skipped).append(spec.name)
    summary = summarize(exp_dir, opts.experiment)
    return {"trained": trained, "skipped": skipped, "failed": failed, "summary": summary}


# ------------------------------------------------------------------------------------------------------------
# Summary


def load_results(exp_dir: Path) -> list[dict[str, Any]]:
    """Every ``result.json`` under ``exp_dir/runs``, sorted by run name."""
    out = []
    for path in sorted((exp_dir / "runs").glob(f"*/{RESULT_FILE}")):
        out.append(json.loads(path.read_text()))
    return out


def _stats(values: Sequence[float | None]) -> dict[str, Any]:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if not v.size:
        return {"mean": None, "std": None, "n": 0, "values": []}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else None, "n": int(v.size),
            "values": [float(x) for x in v]}


def aggregate(results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per grid point (params without the seed): statistics over seeds of every metric.

    Each split's metrics get ``rms_px_400`` and ``rms_px_reproj_400``: pixel errors x 400 / image size, the
    paper's image scale. Runs that did not finish normally (status other than "done") are listed, not
    averaged.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        key = json.dumps({k: v for k, v in r["params"].items() if k != "seed"}, sort_keys=True)
        groups.setdefault(key, []).append(r)
    points = []
    for key, rs in groups.items():
        ok = [r for r in rs if r["status"] == "done"]
        point: dict[str, Any] = {"params": json.loads(key), "seeds": sorted(r["params"]["seed"] for r in ok),
                                 "not_done": {r["run"]: r["status"] for r in rs if r["status"] != "done"},
                                 "image_size": rs[0]["image_size"], "steps": rs[0]["config"]["steps"],
                                 "wall_time_s": _stats([r["wall_time_s"]["total"] for r in rs])["mean"]}
        for split in sorted({s for r in ok for s in r["metrics"]}):
            block = {}
            for m in METRICS:
                block[m] = _stats([r["metrics"][split].get(m) for r in ok if split in r["metrics"]])
            for m in ("rms_px", "rms_px_reproj"):
                block[f"{m}_400"] = _stats([_scaled(r["metrics"][split].get(m), r["image_size"][0])
                                            for r in ok if split in r["metrics"]])
            point[split] = block
        points.append(point)
    order = ("mode", "instances", "labelled", "alpha", "unlabelled")

    def sort_key(p: dict[str, Any]) -> tuple:
        vals = [p["params"].get(k) for k in order]
        return tuple((0, v, "") if isinstance(v, (int, float)) else (1, 0, str(v)) for v in vals)

    points.sort(key=sort_key)
    return points


def _stat(points, split: str, metric: str, **params) -> dict[str, Any] | None:
    """Statistics of ``metric`` on ``split`` at the point with ``params`` (None when absent)."""
    for p in points:
        if all(p["params"].get(k) == v for k, v in params.items()) and split in p:
            return p[split][metric] if p[split][metric]["mean"] is not None else None
    return None


def lower(a: dict[str, Any] | None, b: dict[str, Any] | None, rel: float = 0.02) -> bool | str | None:
    """Is error ``a`` below error ``b`` by more than the noise?

    The margin is the larger of ``rel`` of the larger mean and two standard errors of the difference (from
    the seeds' spread; a single seed contributes none).

    Returns:
        True (lower), False (higher), "within noise", or None when either is missing.
    """
    if a is None or b is None:
        return None

    def se2(s: dict[str, Any]) -> float:
        return (s["std"] ** 2 / s["n"]) if s.get("std") is not None and s["n"] > 1 else 0.0

    margin = max(rel * max(abs(a["mean"]), abs(b["mean"])), 2.0 * math.sqrt(se2(a) + se2(b)))
    if a["mean"] < b["mean"] - margin:
        return True
    if a["mean"] > b["mean"] + margin:
        return False
    return "within noise"


def _smaller(x: float, y: float, tol: float) -> bool | str:
    """x < y by more than ``tol``: True; x > y by more than ``tol``: False; else "within noise"."""
    return True if x < y - tol else False if x > y + tol else "within noise"


def _all(verdicts: Sequence[bool | str | None]) -> bool | str | None:
    """Combine verdicts of a chain: False if any is False, True if all are True, else unclear/None."""
    if not verdicts or any(v is None for v in verdicts):
        return None
    if any(v is False for v in verdicts):
        return False
    return True if all(v is True for v in verdicts) else "within noise"


def _m(s: dict[str, Any] | None) -> str:
    if s is None:
        return "-"
    return _fmt(s["mean"]) + (f" +- {_fmt(s['std'])}" if s.get("std") is not None else "")


def findings(experiment: str, points: list[dict[str, Any]],
             metric: str = "rms_px_400") -> list[dict[str, Any]]:
    """The paper's findings checked against these points.

    Returns:
        ``[{"finding", "measured", "reproduced"}]``; ``reproduced`` is True, False, "within noise" (see
        :func:`lower`) or None when a point it needs is missing.
    """
    out: list[dict[str, Any]] = []

    def add(text: str, measured: str, holds: bool | str | None) -> None:
        out.append({"finding": text, "measured": measured, "reproduced": holds})

    values = lambda key: sorted({p["params"][key] for p in points if key in p["params"]})  # noqa: E731
    unit = "px@400" if metric.endswith("_400") else metric
    if experiment == "label-efficiency":
        Us = values("unlabelled")
        u_max = max(Us) if Us else 0
        for L in values("labelled"):
            base = _stat(points, "test", metric, labelled=L, unlabelled=0)
            s3k = _stat(points, "test", metric, labelled=L, unlabelled=u_max) if u_max else None
            add(f"S3K with {u_max} unlabelled frames beats labels only at {L} labelled",
                f"{_m(s3k)} vs {_m(base)} {unit}", lower(s3k, base))
        for L in (3, 10):
            errs = [_stat(points, "test", metric, labelled=L, unlabelled=U) for U in Us]
            if len(Us) >= 3 and all(e is not None for e in errs):
                add(f"more unlabelled frames, lower error ({L} labelled; unlabelled {Us})",
                    " > ".join(_m(e) for e in errs) + f" {unit}",
                    _all([lower(b, a) for a, b in zip(errs, errs[1:])]))
    elif experiment == "domain-shift":
        Us = values("unlabelled")
        u_max = max(Us) if Us else 0
        for L in values("labelled"):
            for mode in ("start", "full"):
                base = _stat(points, "test", metric, mode=mode, labelled=L, unlabelled=0)
                s3k = (_stat(points, "test", metric, mode=mode, labelled=L, unlabelled=u_max) if u_max
                       else None)
                add(f"{mode} mode, {L} labelled: unlabelled frames over the whole timeline lower the error "
                    "on unseen distractors", f"{_m(s3k)} vs {_m(base)} {unit}", lower(s3k, base))
            st0 = _stat(points, "test", metric, mode="start", labelled=L, unlabelled=0)
            fu0 = _stat(points, "test", metric, mode="full", labelled=L, unlabelled=0)
            add(f"{L} labelled, labels only: labels from the first distractor set only (start) generalize "
                "worse than labels over the whole timeline (full)", f"{_m(st0)} vs {_m(fu0)} {unit}",
                lower(fu0, st0))
            if u_max:
                st = _stat(points, "test", metric, mode="start", labelled=L, unlabelled=u_max)
                fu = _stat(points, "test", metric, mode="full", labelled=L, unlabelled=u_max)
                if st is not None and fu is not None and st0 is not None and fu0 is not None:
                    # gap = start - full: how much worse the start labels generalize. It can only narrow if
                    # there is one without unlabelled frames; "narrower" compares sizes, so a start model
                    # that overtakes full by more than the gap was does not count as closing it.
                    g1, g0 = st["mean"] - fu["mean"], st0["mean"] - fu0["mean"]
                    tol = 0.02 * max(st["mean"], st0["mean"])
                    add(f"{L} labelled: self-supervision narrows the start-vs-full gap",
                        f"gap (start - full) {_fmt(g1)} with vs {_fmt(g0)} without {unit}",
                        _smaller(abs(g1), g0, tol) if g0 > tol else "no gap without unlabelled frames")
    elif experiment == "category":
        ns = values("instances")
        if len(ns) >= 2:
            lo = _stat(points, "test", metric, instances=ns[0])
            hi = _stat(points, "test", metric, instances=ns[-1])
            add(f"more training instances, lower error on the held-out instances ({ns[0]} vs {ns[-1]})",
                f"{_m(lo)} -> {_m(hi)} {unit} (paper {PAPER_CATEGORY_TEST_PX.get(ns[0], '-')} -> "
                f"{PAPER_CATEGORY_TEST_PX.get(ns[-1], '-')})", lower(hi, lo))
            tr = [_stat(points, "train", metric, instances=n) for n in ns]
            te = [_stat(points, "test", metric, instances=n) for n in ns]
            if all(v is not None for v in tr + te):
                trs, tes = cast(list[dict[str, Any]], tr), cast(list[dict[str, Any]], te)
                g0, g1 = tes[0]["mean"] - trs[0]["mean"], tes[-1]["mean"] - trs[-1]["mean"]
                add("the gap between training and held-out instances shrinks with more instances",
                    f"held-out - training: {_fmt(g0)} ({ns[0]}) -> {_fmt(g1)} ({ns[-1]}) {unit}",
                    _smaller(g1, g0, 0.02 * tes[0]["mean"]))
    elif experiment == "alpha":
        alphas = values("alpha")
        best: dict[Any, Any] = {}  # labelled -> the alpha of the lowest error
        for L in values("labelled"):
            by_alpha = {a: _stat(points, "test", metric, labelled=L, alpha=a) for a in alphas}
            found = {a: e for a, e in by_alpha.items() if e is not None}
            if found:
                best[L] = min(found, key=lambda a: found[a]["mean"])
        if len(best) >= 2:
            l_lo, l_hi = min(best), max(best)
            add(f"small alpha is best with few labels, alpha near 1 with more ({l_lo} vs {l_hi} labelled)",
                f"best alpha {best[l_lo]:g} at {l_lo} labelled, {best[l_hi]:g} at {l_hi}",
                best[l_lo] < best[l_hi] if best[l_lo] != best[l_hi] else False)
    return out


def source_revision() -> str | None:
    """The git commit of the s3k source in use (``-dirty`` when its files differ from it), or None when s3k
    is not run from a git checkout or git is unavailable."""
    pkg = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "-C", str(pkg), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10)
        if rev.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(pkg), "status", "--porcelain", "--untracked-files=no", "--",
                                "."], capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return rev.stdout.strip() + ("-dirty" if dirty else "")


def summarize(exp_dir: Path, experiment: str | None = None) -> dict[str, Any]:
    """Write ``summary.json``, the plots and ``README.md`` of one experiment folder from its runs' JSON."""
    exp_dir = Path(exp_dir)
    experiment = experiment or exp_dir.name
    results = load_results(exp_dir)
    points = aggregate(results)
    summary: dict[str, Any] = {
        "experiment": experiment, "description": DESCRIPTIONS.get(experiment, ""),
        "runs": len(results), "scales": sorted({r.get("scale", "?") for r in results}),
        "image_sizes": sorted({r["image_size"][0] for r in results}),
        "steps": sorted({r["config"]["steps"] for r in results}),
        "paper": {"image_size": PAPER_SIZE, "steps": PAPER_STEPS},
        "error_metric": "rms_px_400: rms_px x 400 / image size (pixels at the paper's image scale)",
        "points": points, "findings": findings(experiment, points),
        "generated_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        # provenance as the runs recorded it (runs made before it was recorded count as unrecorded)
        "commands": sorted({r["command"] for r in results if r.get("command")}),
        "code_revisions": sorted({r["code_revision"] for r in results if r.get("code_revision")}),
        "runs_without_provenance": sum(1 for r in results if not r.get("command")),
    }
    if experiment == "category":
        summary["paper"]["category_test_px"] = {str(k): v for k, v in PAPER_CATEGORY_TEST_PX.items()}
    figures = plot(experiment, points, exp_dir)
    summary["figures"] = [p.name for p in figures]
    _write_json(summary, exp_dir / SUMMARY_FILE)
    (exp_dir / "README.md").write_text(readme(summary))
    return summary


# ------------------------------------------------------------------------------------------------------------
# Plots


def _series(points, split: str, metric: str, x_key: str, **where) -> tuple[list, list, list]:
    xs, ys, es = [], [], []
    for p in points:
        if split not in p or not all(p["params"].get(k) == v for k, v in where.items()):
            continue
        s = p[split][metric]
        if s["mean"] is None:
            continue
        xs.append(p["params"][x_key])
        ys.append(s["mean"])
        es.append(s["std"] or 0.0)
    order = np.argsort(xs)
    return [xs[i] for i in order], [ys[i] for i in order], [es[i] for i in order]


_PANELS = (("rms_px_400", f"rms 2D error (px at {PAPER_SIZE} px)"), ("median_mm", "median 3D error (mm)"))


def plot(experiment: str, points: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    """Write the experiment's figures (PNG) to ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    written: list[Path] = []
    sizes = sorted({p["image_size"][0] for p in points})
    steps = sorted({p["steps"] for p in points})
    scale_note = (f"{'/'.join(map(str, sizes))} px, {'/'.join(map(str, steps))} steps "
                  f"(paper: {PAPER_SIZE} px, {PAPER_STEPS // 1000}k batches); bars: std over seeds")

    def figure(name: str, draw: Callable[[Any, str, str], None], title: str, panels=_PANELS) -> None:
        fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4))
        axes = np.atleast_1d(axes)
        for ax, (metric, label) in zip(axes, panels):
            if points:
                draw(ax, metric, label)
            else:
                ax.text(0.5, 0.5, "no finished runs", ha="center", va="center", transform=ax.transAxes)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        fig.suptitle(f"{title}\n{scale_note}", fontsize=9)
        fig.tight_layout()
        path = out_dir / f"{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    values = lambda key: sorted({p["params"][key] for p in points if key in p["params"]})  # noqa: E731
    if experiment == "label-efficiency":
        def per_labelled(ax, metric, label):
            for U in values("unlabelled"):
                x, y, e = _series(points, "test", metric, "labelled", unlabelled=U)
                ax.errorbar(x, y, yerr=e, marker="o", capsize=3,
                            label="labels only (no_unsup)" if U == 0 else f"S3K, {U} unlabelled")
            ax.set_xscale("log")
            ax.set_xlabel("labelled frames")
            ax.legend(fontsize=8)

        figure("error_vs_labelled", per_labelled, "Box: test error per labelled count, one curve per "
               "unlabelled count (paper fig. 4 left)")

        def per_total(ax, metric, label):
            xs, ys, cs = [], [], []
            for p in points:
                s = p["test"][metric] if "test" in p else {"mean": None}
                if s["mean"] is None:
                    continue
                L, U = p["params"]["labelled"], p["params"]["unlabelled"]
                xs.append(L + U)
                ys.append(s["mean"])
                cs.append(L / (L + U))
            sc = ax.scatter(xs, ys, c=cs, cmap="viridis", norm=matplotlib.colors.LogNorm(vmin=1e-3, vmax=1),
                            s=40, edgecolors="k", linewidths=0.4)
            plt.colorbar(sc, ax=ax, label="labelled share L / (L + U)")
            ax.set_xscale("log")
            ax.set_xlabel("total training frames L + U")

        figure("error_vs_total_frames", per_total, "Box: test error against total frames, coloured by the "
               "labelled share (paper fig. 4 right)")
    elif experiment == "domain-shift":
        def per_mode(ax, metric, label):
            for i, U in enumerate(values("unlabelled")):
                for mode, style in (("start", "-"), ("full", "--")):
                    x, y, e = _series(points, "test", metric, "labelled", mode=mode, unlabelled=U)
                    if x:
                        ax.errorbar(x, y, yerr=e, marker="o", capsize=3, linestyle=style, color=f"C{i}",
                                    label=f"{mode}, " + ("labels only" if U == 0 else f"S3K {U} unlabelled"))
            ax.set_xscale("log")
            ax.set_xlabel("labelled frames")
            ax.legend(fontsize=8)

        figure("error_vs_labelled", per_mode, "Distractors: test error on unseen distractor sets; labels "
               "from the first set (start, solid) or all (full, dashed)")
    elif experiment == "category":
        def per_instances(ax, metric, label):
            for split, style in (("train", "--"), ("test", "-")):
                x, y, e = _series(points, split, metric, "instances")
                ax.errorbar(x, y, yerr=e, marker="o", capsize=3, linestyle=style,
                            label=f"{'training' if split == 'train' else 'held-out'} instances")
            if metric == "rms_px_400":
                n = sorted(PAPER_CATEGORY_TEST_PX)
                ax.plot(n, [PAPER_CATEGORY_TEST_PX[k] for k in n], "k:", marker="s",
                        label="paper, held-out (400 px)")
            ax.set_xlabel("training instances")
            ax.legend(fontsize=8)

        figure("error_vs_instances", per_instances, "Category: error on training and held-out instances "
               "(paper sec. 4.3 table)")
    elif experiment == "alpha":
        def per_alpha(ax, metric, label):
            for L in values("labelled"):
                x, y, e = _series(points, "test", metric, "alpha", labelled=L)
                ax.errorbar(x, y, yerr=e, marker="o", capsize=3, label=f"{L} labelled")
            ax.set_xscale("log")
            ax.set_xlabel("alpha (weight of the self-supervised loss)")
            ax.legend(fontsize=8)

        figure("error_vs_alpha", per_alpha, "Box: test error against alpha (paper appendix C)")
    return written


def verdict(reproduced: bool | str | None) -> str:
    """Text of a finding's verdict: yes, no, within noise, not measured."""
    if reproduced is None:
        return "not measured"
    if isinstance(reproduced, str):
        return reproduced
    return "yes" if reproduced else "no"


def readme(summary: dict[str, Any]) -> str:
    """A short Markdown page of a summary: scale, table of points, findings, figures."""
    exp = summary["experiment"]
    sizes = "/".join(map(str, summary["image_sizes"])) or "-"
    steps = "/".join(map(str, summary["steps"])) or "-"
    lines = [f"# {exp}: {summary['description']}", "",
             f"{summary['runs']} runs, scale {', '.join(summary['scales']) or '-'}: {sizes} px images, "
             f"{steps} steps (paper: {PAPER_SIZE} px, {PAPER_STEPS} batches). Errors in pixels are also "
             f"given at the paper's scale (x {PAPER_SIZE} / image size, column `px@400`). "
             "Mean +- std over seeds.", "",
             "Generated by `s3k experiment ... --summarize-only` from `runs/*/result.json`.", ""]
    for c in summary.get("commands", []):
        lines.append(f"Command: `{c}`  ")
    if summary.get("code_revisions"):
        lines.append("Code revision (git, of the s3k package that trained the runs): "
                     + ", ".join(f"`{r}`" for r in summary["code_revisions"]) + "  ")
    if summary.get("runs_without_provenance"):
        lines.append(f"{summary['runs_without_provenance']} run(s) did not record their command and "
                     "revision.")
    if lines[-1] != "":
        lines.append("")
    keys = [k for k in ("mode", "instances", "alpha", "labelled", "unlabelled", "method")
            if any(k in p["params"] for p in summary["points"])]
    splits = ["test"] + (["train"] if any("train" in p for p in summary["points"]) else [])
    head = keys + ["seeds"] + [f"{s} px@400" for s in splits] + [f"{s} median mm" for s in splits]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def cell(s: dict[str, Any]) -> str:
        if s["mean"] is None:
            return "-"
        return _fmt(s["mean"]) + (f" +- {_fmt(s['std'])}" if s["std"] is not None else "")

    for p in summary["points"]:
        row = [str(p["params"].get(k, "")) for k in keys] + [str(len(p["seeds"]))]
        row += [cell(p[s]["rms_px_400"]) if s in p else "-" for s in splits]
        row += [cell(p[s]["median_mm"]) if s in p else "-" for s in splits]
        lines.append("| " + " | ".join(row) + " |")
    if exp == "category":
        lines += ["", "Paper (400 px, held-out instances): " + ", ".join(
            f"{n}: {v}" for n, v in PAPER_CATEGORY_TEST_PX.items()) + " px."]
    lines += ["", "## Findings", "", "| paper finding | measured | reproduced? |", "|---|---|---|"]
    for f in summary["findings"]:
        lines.append(f"| {f['finding']} | {f['measured']} | {verdict(f['reproduced'])} |")
    lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in summary.get("figures", [])]
    return "\n".join(lines) + "\n"


def publish(exp_dir: Path, dest: Path) -> list[Path]:
    """Copy an experiment's summary.json, README.md and figures to ``dest`` (e.g. docs/results/NAME)."""
    dest.mkdir(parents=True, exist_ok=True)
    copied = []
    for path in [exp_dir / SUMMARY_FILE, exp_dir / "README.md", *sorted(exp_dir.glob("*.png"))]:
        if path.is_file():
            shutil.copyfile(path, dest / path.name)
            copied.append(dest / path.name)
    return copied


# ------------------------------------------------------------------------------------------------------------
# Command line


def _int_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _float_list(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def configure_parser(parser: argparse.ArgumentParser) -> None:
    lines = "\n".join(f"  {name:<18} {text}" for name, text in DESCRIPTIONS.items())
    scales = "\n".join(f"  {name:<6} {s.size} px, {s.steps} steps, {s.test} test frames, up to "
                       f"{s.pool_unlabelled} unlabelled, {s.seeds} seed(s) at claim points"
                       for name, s in SCALES.items())
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (f"experiments:\n{lines}\n\nscales:\n{scales}\n\nA finished run (runs/NAME/result.json) "
                     "is never redone: rerun the same command to continue a killed sweep.")
    parser.add_argument("name", choices=EXPERIMENTS, metavar="NAME",
                        help="experiment: " + ", ".join(EXPERIMENTS))
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="workspace: data/ (shared by experiments), NAME/runs/, NAME/summary.json, plots")
    parser.add_argument("--scale", choices=list(SCALES), default="small",
                        help="toy (seconds; tests), small (about 1 h per experiment on 2 CPU cores), full "
                             "(whole grid, default training scale; hours). Default: small")
    parser.add_argument("--seeds", type=int, default=None, help="seeds at the points carrying a claim "
                        "(default: the scale's)")
    parser.add_argument("--seeds-other", type=int, default=1, help="seeds at the other points (default 1)")
    parser.add_argument("--steps", type=int, default=None,
                        help="training steps per run (default: the scale's)")
    parser.add_argument("--size", type=int, default=None, metavar="PX",
                        help="image size in pixels (default: the scale's)")
    parser.add_argument("--test", type=int, default=None, help="test frames (default: the scale's)")
    parser.add_argument("--data-seed", type=int, default=0, help="seed of the rendered datasets (default 0)")
    parser.add_argument("--labelled", type=_int_list, default=None, metavar="N,N,...",
                        help="labelled counts of the grid")
    parser.add_argument("--unlabelled", type=_int_list, default=None, metavar="N,N,...",
                        help="unlabelled counts of the grid (0: labels-only baseline)")
    parser.add_argument("--instances", type=_int_list, default=None, metavar="N,N,...",
                        help="category: training instance counts")
    parser.add_argument("--alphas", type=_float_list, default=None, metavar="A,A,...",
                        help="alpha: values of alpha")
    parser.add_argument("--modes", type=lambda s: [m for m in s.split(",") if m], default=None,
                        metavar="start,full", help="domain-shift: labelling modes")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="any TrainConfig field for every run (repeatable), e.g. --set lr=0.002")
    parser.add_argument("--device", default="cpu", help="'cpu', 'cuda', 'auto' (default: cpu)")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch threads per run (0: torch's default; 1 when running two sweeps at once)")
    parser.add_argument("--workers", type=int, default=None, help="rendering processes (default: CPUs)")
    parser.add_argument("--dry-run", action="store_true", help="print the runs and the estimate, run nothing")
    parser.add_argument("--summarize-only", action="store_true",
                        help="only (re)write summary.json, plots and README.md from the finished runs")
    parser.add_argument("--publish", default=None, metavar="DIR",
                        help="then copy summary.json, README.md and plots to DIR (e.g. docs/results/NAME)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def options_from_args(args: argparse.Namespace) -> Options:
    """:class:`Options` from parsed arguments; ``--set`` values are checked against TrainConfig."""
    overrides: dict[str, Any] = {}
    for item in args.set:
        if "=" not in item:
            raise ValueError(f"--set: expected FIELD=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        overrides[k.strip().replace("-", "_")] = v.strip()
    config_from_dict(TrainConfig, overrides, where="--set")  # names the bad field or value
    for name in ("seeds", "steps", "size", "test"):
        v = getattr(args, name)
        if v is not None and v <= 0:
            raise ValueError(f"--{name}: must be > 0, got {v}")
    return Options(experiment=args.name, out=Path(args.out), scale=args.scale, seeds=args.seeds,
                   seeds_other=args.seeds_other, steps=args.steps, size=args.size, test=args.test,
                   data_seed=args.data_seed, labelled=args.labelled, unlabelled=args.unlabelled,
                   instances=args.instances, alphas=args.alphas, modes=args.modes,
                   train_overrides=overrides, device=args.device, threads=args.threads, workers=args.workers,
                   progress=not args.no_progress, command=getattr(args, "command_line", None))


def run(args: argparse.Namespace) -> int:
    def log(msg: str) -> None:
        print(msg, flush=True)

    exp_dir = Path(args.out) / args.name
    if args.summarize_only:
        if not (exp_dir / "runs").is_dir():
            print(f"s3k experiment: {exp_dir / 'runs'} does not exist: nothing to summarize", file=sys.stderr)
            return 2
        summary = summarize(exp_dir, args.name)
    else:
        try:
            opts = options_from_args(args)
            runs = plan(opts)
        except ValueError as exc:
            print(f"s3k experiment: {exc}", file=sys.stderr)
            return 2
        if args.dry_run:
            log(describe_plan(runs, exp_dir, Path(args.out) / "data", args.scale))
            for r in runs:
                log(f"  {r.name:<28} pool {r.pool.name}, ~{r.estimated_cpu_s() / 60:.1f} CPU-min")
            return 0
        try:
            outcome = run_experiment(opts, log)
        except ValueError as exc:
            print(f"s3k experiment: {exc}", file=sys.stderr)
            return 2
        summary = outcome["summary"]
        log(f"trained {len(outcome['trained'])}, already finished or held elsewhere "
            f"{len(outcome['skipped'])}, failed {len(outcome['failed'])}")
    log(f"summary: {exp_dir / SUMMARY_FILE} ({summary['runs']} runs, {len(summary['points'])} points); "
        f"figures: {', '.join(summary['figures'])}")
    for f in summary["findings"]:
        log(f"  {verdict(f['reproduced']):<12} {f['finding']}: {f['measured']}")
    if args.publish:
        copied = publish(exp_dir, Path(args.publish))
        log(f"published {len(copied)} files to {args.publish}")
    if not args.summarize_only and outcome["failed"]:
        return 1
    return 0
