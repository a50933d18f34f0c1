"""``s3k demo``: the recommended configuration on the box scene, S3K against labels only, side by side.

Steps (each skipped when its output already exists, so an interrupted demo continues where it stopped):

1. ``DIR/pool``: the box scene rendered at 384 px (MuJoCo): 100 labelled, 2000 unlabelled and 200 test
   frames. ``DIR/data``: the dataset trained on, 10 of the 100 labelled frames as a labeller following the
   labelling app's *poses in proportion* ranking would pick them, all unlabelled and test frames
   (:func:`s3k.experiments.accuracy.labelled_view`).
2. ``DIR/s3k`` and ``DIR/baseline``: ``s3k train --preset box-fast`` (the README's headline configuration
   on smaller crops, two thirds of its CPU time, :mod:`s3k.train.presets`; ``--preset box-headline`` for the
   headline's own)
   with and without the self-supervised term (``--no-unsup``): same
   labels, same seed, same steps. On a machine with at least two cores they train at the same time as two
   processes of one thread each (``--sequential``: one after the other).
3. Both evaluated on the test frames through both passes; the table is printed and written with a picture to
   ``DIR/report``: ``demo.png`` (test frames of every camera with the true and detected keypoints, the 3D
   error distributions, the table: :mod:`s3k.experiments.demo_figure`), ``comparison.md``,
   ``comparison.json`` and one evaluation report per model.

``--quick`` runs a tiny version (64 px, a few dozen frames and steps) in about a minute; its numbers only
show that the pipeline works.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from s3k.base.messages import say
from s3k.base.metrics import mm_per_unit
from s3k.base.outputs import check_folder, claim_folder, made_by_s3k, owns_run
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.data.frames import FrameStore
from s3k.detector import Detector, evaluate_store
from s3k.experiments.accuracy import labelled_view
from s3k.experiments.demo_figure import demo_figure, frame_detections
from s3k.inference.report import write_report
from s3k.run_folder import RunFolder
from s3k.train.presets import preset


@dataclass
class DemoConfig:
    """What the demo renders and how it trains: ``preset`` plus ``options`` (more ``s3k train`` options)."""

    size: int = 384
    label_pool: int = 100
    labelled: int = 10
    label_choice: str = "representative"
    unlabelled: int = 2000
    test: int = 200
    preset: str = "box-fast"
    options: tuple[str, ...] = field(default_factory=tuple)
    seed: int = 0

    def train_config(self, own: list[str] | tuple[str, ...] = (), threads: int = 1) -> TrainConfig:
        """The :class:`s3k.config.TrainConfig` of one of the demo's models: the preset, the demo's seed,
        ``threads``, no progress bar, the model's ``own`` options and ``options`` over it."""
        cfg = preset(self.preset).replace(seed=self.seed, threads=threads, progress=False)
        return cfg.with_options([*own, *self.options], where="the demo's options")

    def steps(self) -> tuple[int, int]:
        """``(coarse pass steps, refining pass steps)`` of the preset with ``options`` over it."""
        cfg = self.train_config()
        steps, passes = cfg.schedule.steps, cfg.passes
        return (passes.coarse_steps or steps) if passes.two_pass else 0, steps


QUICK = DemoConfig(size=64, label_pool=20, unlabelled=40, test=12, options=(
    "--steps", "40", "--coarse-steps", "40", "--coarse-size", "32", "--crop-size", "32", "--warmup-steps",
    "10", "--ramp-steps", "10", "--val-every", "20", "--checkpoint-every", "20"))

MODELS = {"labels only": ("baseline", ["--no-unsup"]), "S3K": ("s3k", [])}
"""Model name -> (run folder, its own ``s3k train`` options)."""


def train_command(demo: DemoConfig, data: Path, folder: Path, own: list[str], threads: int = 1) -> list[str]:
    """The ``s3k train`` command of one of the demo's models, built from its configuration
    (:meth:`DemoConfig.train_config`): each model trains in a process of its own, side by side."""
    return [sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(folder), "--resume",
            *demo.train_config(own, threads).to_argv()]


def _finished(folder: Path) -> bool:
    return RunFolder(folder).is_complete()


def comparison_table(results: dict[str, dict]) -> str:
    """Markdown table of the metrics of docs/method.md#metrics (the README's headline's), one row per
    model."""
    metrics = ("median_mm", "rms_mm", "pck_5mm", "pck_10mm", "rms_px")

    def cell(m: dict, k: str) -> str:
        if m.get(k) is None:
            return "-"
        return f"{100 * m[k]:.1f}%" if k.startswith("pck") else f"{m[k]:.2f}"

    lines = ["| model | " + " | ".join(metrics) + " |", "|---|" + "---|" * len(metrics)]
    for name, m in results.items():
        lines.append(f"| {name} | " + " | ".join(cell(m, k) for k in metrics) + " |")
    return "\n".join(lines)


def _train_side_by_side(jobs: list[tuple[str, Path, list[str]]], log, progress: bool = False,
                        totals: tuple[int, int] = (0, 0)) -> dict[str, float]:
    """Run every job's ``s3k train`` command at once, each a process of one thread; returns wall times.

    With ``progress`` each job gets a live bar (step, rate, ETA from the run's ``progress.json``, and its last
    validation figures); without, the last validation of each is logged every minute.
    """
    procs = []
    for name, folder, cmd in jobs:
        folder.parent.mkdir(parents=True, exist_ok=True)
        console = open(folder.parent / f"{folder.name}.console.txt", "a")
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        log(f"[demo] training {name}: {' '.join(cmd)}")
        procs.append((name, folder, subprocess.Popen(cmd, stdout=console, stderr=subprocess.STDOUT, env=env),
                      console, time.perf_counter()))
    coarse_steps = totals[0]
    # after the commands are logged, so that no log line lands between the bars
    bars = _ProgressBars([(n, f, sum(totals)) for n, f, _ in jobs], coarse_steps) if progress else None
    times: dict[str, float] = {}
    last = time.perf_counter()
    while procs:
        time.sleep(2 if bars is not None else 5)
        if bars is not None:
            bars.update()
        for item in list(procs):
            name, folder, proc, console, start = item
            if proc.poll() is None:
                continue
            console.close()
            procs.remove(item)
            times[f"train_{folder.name}_s"] = time.perf_counter() - start
            if proc.returncode != 0:
                for _, _, other, _, _ in procs:
                    other.terminate()
                if bars is not None:
                    bars.close()
                raise RuntimeError(f"training {name} failed (exit {proc.returncode}); see "
                                   f"{RunFolder(folder).log} and "
                                   f"{folder.parent / (folder.name + '.console.txt')}")
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
    def step(run: RunFolder) -> int | None:
        try:
            return int(json.loads(run.progress.read_text())["step"])
        except (OSError, ValueError, KeyError):
            return None

    run = RunFolder(folder)
    if not coarse_steps:
        return step(run), folder
    fine = step(run.fine)
    if fine is not None:
        return coarse_steps + fine, run.fine.path
    return step(run.coarse), run.coarse.path


def _short_validation(folder: Path) -> str:
    """The last validation's 3D figures, e.g. ``val median 7.7 mm, rms 9.4 mm`` (empty before the first)."""
    text = _last_validation(folder)
    parts = dict(p.strip().split(" ", 1) for p in text.split(":", 1)[-1].split(",") if " " in p.strip())
    if "median_mm" not in parts:
        return ""
    return f"val median {parts['median_mm']} mm, rms {parts.get('rms_mm', '?')} mm"


def _last_validation(folder: Path) -> str:
    try:
        lines = [x for x in RunFolder(folder).log.read_text().splitlines() if "validation:" in x]
    except OSError:
        return "starting"
    return lines[-1].split("INFO ", 1)[-1] if lines else "warming up"


def _data(out: Path, demo: DemoConfig, progress: bool, log, timings: dict[str, float]) -> Path:
    """Render the pool and make the labelled view (each once); returns the dataset trained on."""
    from s3k.sim.generate import SimulateConfig, simulate

    pool, data = out / "pool", out / "data"
    if not (pool / "s3k.json").is_file():
        log(f"[demo] simulating the box scene into {pool} ({demo.label_pool} labelled, {demo.unlabelled} "
            f"unlabelled, {demo.test} test frames, {demo.size} px)")
        t = time.perf_counter()
        sim = SimulateConfig(scene="box", size=demo.size, labelled=demo.label_pool,
                             unlabelled=demo.unlabelled, test=demo.test, seed=demo.seed)
        simulate(sim, pool, workers=min(2, os.cpu_count() or 1), progress=progress, overwrite=True)
        timings["simulate_s"] = time.perf_counter() - t
    if demo.label_pool == demo.labelled:
        return pool
    if not (data / "s3k.json").is_file():
        log(f"[demo] choosing {demo.labelled} of the {demo.label_pool} labelled frames ({demo.label_choice})")
        t = time.perf_counter()
        labelled_view(pool, data, demo.label_choice, demo.seed, labelled=demo.labelled)
        timings["label_choice_s"] = time.perf_counter() - t
    return data


def _evaluate(out: Path, data: Path, log) -> tuple[dict[str, dict], dict[str, object]]:
    """Both models on the test frames: their metrics (and reports), and their 3D errors in mm."""

    ds = Dataset.open(data, cache="none")
    store = FrameStore(ds, ds.frames("test"), preload_mb=0, labels=True, points=True)
    results, errors = {}, {}
    for name, (folder, _) in MODELS.items():
        log(f"[demo] evaluating {name} on the test frames")
        metrics, arrays = evaluate_store(Detector.load(out / folder, "cpu"), store, 16, ds.units, keep=6)
        metrics["split"] = "test"
        write_report(out / "report" / folder, metrics, arrays, mm_per_unit(ds.units), title=f"{name} (test)")
        results[name] = metrics
        sel = arrays["X_valid"] & arrays["X_gt_mask"]
        errors[name] = np.linalg.norm(arrays["X"] - arrays["X_gt"], axis=-1)[sel] * mm_per_unit(ds.units)
    return results, errors


DEMO_NAMES = frozenset({"pool", "data", "s3k", "baseline", "report"})
"""What a demo folder holds (its hidden neighbours of an interrupted rendering aside)."""


def is_demo_folder(folder: Path) -> bool:
    """True when ``folder`` holds a demo of an earlier call (made before demo folders were marked): only the
    demo's own folders, one of them its dataset or a run."""
    names = {p.name for p in folder.iterdir() if not p.name.startswith(".")}
    return names <= DEMO_NAMES and any(made_by_s3k(folder / n) or owns_run(folder / n)
                                       for n in ("pool", "data", "s3k", "baseline"))


def run_demo(out: str | Path, demo: DemoConfig, progress: bool = True, log=say,
             parallel: bool = True) -> dict:
    """Run the whole demo into ``out``; returns ``{"labels only": metrics, "S3K": metrics, ...}``."""

    # a new or empty folder, or an earlier demo: never someone's files
    out = check_folder(out, "demo", owns=is_demo_folder, ours=DEMO_NAMES)
    claim_folder(out, "demo")
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    data = _data(out, demo, progress, log, timings)
    todo = [(name, out / folder, own) for name, (folder, own) in MODELS.items()
            if not _finished(out / folder)]
    if parallel and len(todo) > 1 and (os.cpu_count() or 1) >= 2:  # one thread each, side by side
        jobs = [(name, folder, train_command(demo, data, folder, own)) for name, folder, own in todo]
        timings.update(_train_side_by_side(jobs, log, progress=progress, totals=demo.steps()))
    else:
        for name, folder, own in todo:  # one after the other, torch's default threads
            log(f"[demo] training {name} into {folder}")
            t = time.perf_counter()
            subprocess.run(train_command(demo, data, folder, own, threads=0), check=True,
                           stdout=None if progress else subprocess.DEVNULL)
            timings[f"train_{folder.name}_s"] = time.perf_counter() - t

    torch.set_num_threads(1)  # the evaluation is short; one thread is robust on a shared machine
    t = time.perf_counter()
    results, errors = _evaluate(out, data, log)
    timings["evaluate_s"] = time.perf_counter() - t
    timings["this_call_s"] = time.perf_counter() - t0
    report = out / "report"
    previous = report / "comparison.json"
    if previous.is_file():  # stages reused from an earlier call keep the times they took then
        try:
            earlier = json.loads(previous.read_text()).get("timings", {})
        except (OSError, ValueError):
            earlier = {}
        timings = {**{k: v for k, v in earlier.items() if k not in ("this_call_s", "total_s")}, **timings}
    stages = [v for k, v in timings.items() if k.startswith("train_")]
    if "simulate_s" in timings and len(stages) == 2:
        train_wall = max(stages) if parallel else sum(stages)
        timings["total_s"] = (timings["simulate_s"] + timings.get("label_choice_s", 0.0) + train_wall
                              + timings.get("evaluate_s", 0.0))
    coarse, fine = demo.steps()
    scale = (f"box scene rendered at {demo.size} px, {demo.labelled} labelled ({demo.label_choice} choice of "
             f"{demo.label_pool}) + {demo.unlabelled} unlabelled frames, {demo.test} test frames; "
             f"s3k train --preset {demo.preset} {' '.join(demo.options)}".rstrip()
             + f" ({coarse} + {fine} steps per model; the paper: 400 px, 150k steps)")
    table = comparison_table(results)
    report.mkdir(parents=True, exist_ok=True)
    (report / "comparison.md").write_text(f"# S3K vs labels only\n\n{scale}\n\n{table}\n")
    summary = {"scale": scale, "config": {**demo.__dict__, "options": list(demo.options)}, "timings": timings,
               **results}
    (report / "comparison.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    _picture(report / "demo.png", data, results, errors, scale)
    return summary


def _picture(path: Path, data: Path, results: dict[str, dict], errors, scale: str) -> None:
    ds = Dataset.open(data, cache="none")
    test = ds.frames("test")
    shown = test[np.linspace(0, len(test) - 1, min(2, len(test))).astype(int)]
    out = path.parent.parent
    found = {name: frame_detections(out / folder, ds, shown) for name, (folder, _) in MODELS.items()}
    metrics = ("median_mm", "rms_mm", "pck_10mm")
    rows = [["model", "median mm", "RMS mm", "within 10 mm"]]
    for name, m in results.items():
        rows.append([name] + ["-" if m.get(k) is None else (f"{100 * m[k]:.1f}%" if k == "pck_10mm"
                                                             else f"{m[k]:.2f}") for k in metrics])
    demo_figure(path, ds, shown, found, errors, rows, title=f"s3k demo: {scale.split(';')[0]}")
