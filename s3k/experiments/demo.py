"""``s3k demo``: simulate the box scene, train S3K and the labels-only baseline on the same labels, compare.

Steps (each skipped when its output already exists, so an interrupted demo continues where it stopped):

1. ``DIR/data``: the box scene at 256 px, 10 labelled, 2000 unlabelled and 200 test frames (MuJoCo).
2. ``DIR/baseline``: the coarse-to-fine detector (``s3k train --two-pass``: a coarse pass on the whole image
   at 96 px, a refining pass on 128 px crops around its estimate) trained on the 10 labelled frames only
   (``--no-unsup``).
3. ``DIR/s3k``: the same detector, same labels, same seed, plus the self-supervised multi-view term on the
   unlabelled frames in both passes (labels-only warm-up, then a ramp of alpha), its pseudo-labels held to
   the box's labelled layout (``--layout_tol 0.2``: the box is rigid).
   Both augment with rotations up to 180 degrees in the coarse pass and up to 15 in the refining pass
   (``--coarse-rotation 180 --rotation_deg 15``), as the accuracy benchmark's headline does.
4. Both evaluated on the same test frames through both passes; the side-by-side table is printed and written
   with plots to ``DIR/report`` (``comparison.md``, ``comparison.json``, ``comparison.png`` and one report per
   model).

The two trainings are independent, so on a machine with at least two cores they run at the same time as two
``s3k train`` processes of one thread each (``--sequential`` trains one after the other with torch's default
threads). On a shared 2-core CPU one thread per process is also much faster than two threads per process:
OpenMP threads that wait for a busy core stall every convolution. ``--one-pass`` trains one network on the
whole image at 96 px instead (the demo before the coarse-to-fine detector). ``--quick`` runs a tiny version
(48 px, a few dozen frames and steps) in under a minute; its numbers only show that the pipeline works.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from s3k.config import TrainConfig, default_of
from s3k.detector import PROGRESS_FILE


@dataclass
class DemoConfig:
    """Sizes of the demo; the self-supervision schedule and the seed start from ``TrainConfig``'s."""

    size: int = 256
    labelled: int = 10
    unlabelled: int = 2000
    test: int = 200
    steps: int = 2000
    two_pass: bool = True
    coarse_size: int = 96
    coarse_steps: int = 2000
    crop_size: int = 128
    # rotations of the augmentation, degrees: the coarse pass (or the one pass) must find the box in any pose,
    # the refining pass sees crops the coarse pass has placed and is more precise with narrow ones
    coarse_rotation: float = 180.0
    rotation_deg: float = 15.0
    warmup_steps: int = default_of("warmup_steps")
    ramp_steps: int = default_of("ramp_steps")
    alpha: float = default_of("alpha")
    layout_tol: float = 0.2  # the box is rigid: S3K's pseudo-labels are held to the labelled corners' layout
    seed: int = default_of("seed")


def schedule_for(steps: int) -> dict[str, int]:
    """Warm-up and ramp lengths for a run of ``steps``: the defaults, or a quarter of the run when shorter."""
    return {name: min(default_of(name), steps // 4) for name in ("warmup_steps", "ramp_steps")}


QUICK = DemoConfig(size=64, labelled=10, unlabelled=40, test=12, steps=40, warmup_steps=10, ramp_steps=10,
                   coarse_size=32, coarse_steps=40, crop_size=32)


def _pass_options(demo: DemoConfig) -> list[str]:
    """The ``s3k train`` options of the demo's detector besides its configuration file."""
    if not demo.two_pass:
        return []
    return ["--two-pass", "--coarse-size", str(demo.coarse_size), "--coarse-steps", str(demo.coarse_steps),
            "--coarse-rotation", f"{demo.coarse_rotation:g}", "--crop-size", str(demo.crop_size)]


def _total_steps(demo: DemoConfig) -> int:
    return demo.coarse_steps + demo.steps if demo.two_pass else demo.steps


def _finished(folder: Path, demo: DemoConfig) -> bool:
    return (folder / ("two_pass.json" if demo.two_pass else "model.pt")).is_file()


def comparison_table(results: dict[str, dict]) -> str:
    """Markdown table of the metrics of docs/method.md#metrics, one row per model."""
    metrics = ("rms_px", "rms_px_reproj", "median_mm", "rms_mm")
    lines = ["| model | " + " | ".join(metrics) + " |", "|---|" + "---|" * len(metrics)]
    for name, m in results.items():
        cells = ["-" if m.get(k) is None else f"{m[k]:.2f}" for k in metrics]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _plot(results: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    names = list(results)
    panels = ((axes[0], ("rms_px", "rms_px_reproj"), "px"), (axes[1], ("median_mm", "rms_mm"), "mm"))
    for ax, group, unit in panels:
        x = np.arange(len(group))
        for i, name in enumerate(names):
            vals = [results[name].get(g) or 0 for g in group]
            ax.bar(x + (i - (len(names) - 1) / 2) * 0.35, vals, 0.35, label=name)
        ax.set_xticks(x, group)
        ax.set_ylabel(unit)
        ax.legend()
    fig.suptitle("box scene: S3K vs labels only (test frames)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _train_side_by_side(jobs: list[tuple[str, Path, TrainConfig]], data: Path, log,
                        progress: bool = False, options: list[str] | None = None,
                        coarse_steps: int = 0) -> dict[str, float]:
    """Train every job at once, each as an ``s3k train`` process with one thread; returns wall times.

    With ``progress`` each job gets a live bar (step, rate, ETA from the run's ``progress.json``, and its last
    validation figures); without, the last validation of each is logged every minute.
    """
    procs = []
    for name, folder, cfg in jobs:
        folder.mkdir(parents=True, exist_ok=True)
        cfg_file = folder.parent / f"{folder.name}.train.json"
        cfg_file.write_text(json.dumps(cfg.replace(threads=1, progress=False).to_dict(), indent=2))
        cmd = [sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(folder), "--resume",
               "--config", str(cfg_file), *(options or [])]
        console = open(folder.parent / f"{folder.name}.console.txt", "a")
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        log(f"[demo] training {name}: {' '.join(cmd)}")
        procs.append((name, folder, cfg, subprocess.Popen(cmd, stdout=console, stderr=subprocess.STDOUT,
                                                          env=env), console, time.perf_counter()))
    # after the commands are logged, so that no log line lands between the bars
    totals = [(name, folder, coarse_steps + cfg.steps) for name, folder, cfg in jobs]
    bars = _ProgressBars(totals, coarse_steps) if progress else None
    times: dict[str, float] = {}
    last = time.perf_counter()
    while procs:
        time.sleep(2 if bars is not None else 5)
        if bars is not None:
            bars.update()
        for item in list(procs):
            name, folder, cfg, proc, console, start = item
            if proc.poll() is None:
                continue
            console.close()
            procs.remove(item)
            times[f"train_{folder.name}_s"] = time.perf_counter() - start
            if proc.returncode != 0:
                for _, _, _, other, _, _ in procs:
                    other.terminate()
                if bars is not None:
                    bars.close()
                raise RuntimeError(f"training {name} failed (exit {proc.returncode}); see {folder}/train.log "
                                   f"and {folder.parent / (folder.name + '.console.txt')}")
            if bars is None:
                log(f"[demo] {name} trained in {times[f'train_{folder.name}_s'] / 60:.1f} min")
        if bars is None and procs and time.perf_counter() - last > 60:
            last = time.perf_counter()
            log("[demo] " + "; ".join(f"{n}: {_last_validation(_current_pass(f, coarse_steps)[1])}"
                                      for n, f, *_ in procs))
    if bars is not None:
        bars.update()
        bars.close()
        for name, folder, _ in jobs:
            log(f"[demo] {name} trained in {times[f'train_{folder.name}_s'] / 60:.1f} min")
    return times


class _ProgressBars:
    """One tqdm bar per training, fed from each run's ``progress.json`` and ``train.log``."""

    def __init__(self, jobs: list[tuple[str, Path, int]], coarse_steps: int = 0) -> None:
        from tqdm import tqdm

        self.coarse_steps = coarse_steps
        width = max(len(name) for name, _, _ in jobs)
        self.jobs = [(folder, tqdm(total=steps, desc=f"{name:<{width}}", position=i, dynamic_ncols=True,
                                   unit="step", smoothing=0.1))
                     for i, (name, folder, steps) in enumerate(jobs)]

    def update(self) -> None:
        for folder, bar in self.jobs:
            step, current = _current_pass(folder, self.coarse_steps)
            if step is None:
                continue
            if step > bar.n:
                bar.update(step - bar.n)
            bar.set_postfix_str(_short_validation(current), refresh=True)

    def close(self) -> None:
        for _, bar in self.jobs:
            bar.close()


def _current_pass(folder: Path, coarse_steps: int) -> tuple[int | None, Path]:
    """``(steps done over both passes, the folder of the pass under way)`` of a run (None before its first
    step); a one-pass run is its own pass."""
    def step(run: Path) -> int | None:
        try:
            return int(json.loads((run / PROGRESS_FILE).read_text())["step"])
        except (OSError, ValueError, KeyError):
            return None

    if not coarse_steps:
        return step(folder), folder
    fine = step(folder / "fine")
    if fine is not None:
        return coarse_steps + fine, folder / "fine"
    return step(folder / "coarse"), folder / "coarse"


def _short_validation(folder: Path) -> str:
    """The last validation's 3D figures, e.g. ``val median 7.7 mm, rms 9.4 mm`` (empty before the first)."""
    text = _last_validation(folder)
    parts = dict(p.strip().split(" ", 1) for p in text.split(":", 1)[-1].split(",") if " " in p.strip())
    if "median_mm" not in parts:
        return ""
    return f"val median {parts['median_mm']} mm, rms {parts.get('rms_mm', '?')} mm"


def _last_validation(folder: Path) -> str:
    try:
        lines = [x for x in (folder / "train.log").read_text().splitlines() if "validation:" in x]
    except OSError:
        return "starting"
    return lines[-1].split("INFO ", 1)[-1] if lines else "warming up"


def run_demo(out: str | Path, demo: DemoConfig, progress: bool = True, log=print,
             parallel: bool = True) -> dict:
    """Run the whole demo into ``out``; returns ``{"baseline": metrics, "s3k": metrics, ...}``."""
    from s3k.inference.evaluate import evaluate_run
    from s3k.sim.generate import SimulateConfig, simulate
    from s3k.train import train
    from s3k.train.two_pass import train_two_pass

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    data = out / "data"
    timings: dict[str, float] = {}
    if not (data / "s3k.json").is_file():
        log(f"[demo] simulating the box scene into {data} ({demo.labelled} labelled, {demo.unlabelled} "
            f"unlabelled, {demo.test} test frames, {demo.size} px)")
        t = time.perf_counter()
        sim = SimulateConfig(scene="box", size=demo.size, labelled=demo.labelled, unlabelled=demo.unlabelled,
                             test=demo.test, seed=demo.seed)
        simulate(sim, data, progress=progress, overwrite=True)
        timings["simulate_s"] = time.perf_counter() - t
    base_cfg = TrainConfig.from_flat(steps=demo.steps, warmup_steps=demo.warmup_steps,
                                     ramp_steps=demo.ramp_steps, alpha=demo.alpha, seed=demo.seed,
                                     layout_tol=demo.layout_tol, rotation_deg=demo.rotation_deg,
                                     progress=progress, val_every=max(demo.steps // 6, 1),
                                     checkpoint_every=max(demo.steps // 6, 1))
    if not demo.two_pass:
        base_cfg = base_cfg.replace(image_size=demo.coarse_size, rotation_deg=demo.coarse_rotation)
    runs = {"labels only": base_cfg.replace(unsup=False), "S3K": base_cfg}
    folders = {"labels only": out / "baseline", "S3K": out / "s3k"}
    results: dict[str, dict] = {}
    todo = [(n, folders[n], cfg) for n, cfg in runs.items() if not _finished(folders[n], demo)]
    if parallel and len(todo) > 1 and (os.cpu_count() or 1) >= 2:
        timings.update(_train_side_by_side(todo, data, log, progress=progress, options=_pass_options(demo),
                                           coarse_steps=demo.coarse_steps if demo.two_pass else 0))
        import torch

        torch.set_num_threads(1)  # the evaluation below is short; one thread is robust on a shared machine
    else:
        for name, folder, cfg in todo:
            log(f"[demo] training {name} ({_total_steps(demo)} steps) into {folder}")
            t = time.perf_counter()
            if demo.two_pass:
                train_two_pass(data, folder, cfg, coarse_size=demo.coarse_size,
                               coarse_steps=demo.coarse_steps, coarse_rotation=demo.coarse_rotation,
                               crop_size=demo.crop_size, resume=True, log=log)
            else:
                result = train(data, folder, cfg, resume=True)
                if result.status != "done":
                    raise RuntimeError(f"training {name} stopped early ({result.status}); see "
                                       f"{folder}/train.log")
            timings[f"train_{folder.name}_s"] = time.perf_counter() - t
    t = time.perf_counter()
    for name, folder in folders.items():
        log(f"[demo] evaluating {name} on the test frames")
        results[name] = evaluate_run(folder, data, "test", report=out / "report" / folder.name)
    timings["evaluate_s"] = time.perf_counter() - t
    timings["this_call_s"] = time.perf_counter() - t0
    ran = [k[:-2] for k in timings if k.endswith("_s") and k != "this_call_s"]
    previous = out / "report" / "comparison.json"
    if previous.is_file():  # stages reused from an earlier call keep the times they took then
        try:
            earlier = json.loads(previous.read_text()).get("timings", {})
        except (OSError, ValueError):
            earlier = {}
        timings = {**{k: v for k, v in earlier.items() if k not in ("this_call_s", "total_s")}, **timings}
    stages = [v for k, v in timings.items() if k.startswith("train_")]
    if "simulate_s" in timings and len(stages) == 2:
        # wall time of the whole demo: simulation, the trainings (side by side or one after the other), and
        # the evaluation of this call
        train_wall = max(stages) if timings.get("parallel", parallel) else sum(stages)
        timings["total_s"] = timings["simulate_s"] + train_wall + timings.get("evaluate_s", 0.0)
    timings.setdefault("parallel", parallel)
    table = comparison_table(results)
    report = out / "report"
    report.mkdir(parents=True, exist_ok=True)
    passes = (f"two passes: coarse {demo.coarse_size} px, {demo.coarse_steps} steps, rotations up to "
              f"{demo.coarse_rotation:g} deg; crops {demo.crop_size} px, {demo.steps} steps, up to "
              f"{demo.rotation_deg:g} deg" if demo.two_pass
              else f"one pass at {demo.coarse_size} px, {demo.steps} steps, rotations up to "
                   f"{demo.coarse_rotation:g} deg")
    scale = (f"box scene rendered at {demo.size} px, {demo.labelled} labelled + {demo.unlabelled} unlabelled "
             f"frames, {demo.test} test frames; {passes} per model (the paper: 400 px, 150k steps)")
    (report / "comparison.md").write_text(f"# S3K vs labels only\n\n{scale}\n\n{table}\n")
    summary = {"scale": scale, "config": demo.__dict__, "timings": timings, "stages_run_in_this_call": ran,
               **{name: results[name] for name in results}}
    (report / "comparison.json").write_text(json.dumps(summary, indent=2) + "\n")
    _plot(results, report / "comparison.png")
    return summary
