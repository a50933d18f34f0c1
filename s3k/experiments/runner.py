"""Running a sweep: each run trained, evaluated and recorded once, resumable, shareable between processes.

A run with a ``result.json`` is never redone (and one made with other settings is refused); a run killed
during training continues from its last checkpoint. Several invocations may share a workspace: each run is
claimed with a lock on ``run.lock`` beside it, and a run whose lock is held by a live process is skipped.
The lock is the kernel's (``flock``), so a process killed at any moment leaves no stale claim.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json, file_lock
from s3k.base.messages import say
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.detector import CHECKPOINT_FILE
from s3k.experiments.findings import fmt
from s3k.experiments.grid import (
    DESCRIPTIONS,
    RENDER_IMAGES_PER_S,
    RESULT_FILE,
    Options,
    RunSpec,
    plan,
)
from s3k.experiments.report import source_revision, summarize
from s3k.experiments.views import drop_cache, ensure_pool, make_view, select_frames
from s3k.inference.evaluate import evaluate_run
from s3k.run_folder import RunFolder
from s3k.train import read_checkpoint_step, train

#: Config fields that do not change a run's result: a finished run is kept when only these differ.
_NEUTRAL_FIELDS = ("progress", "device", "threads", "preload_mb", "val_every", "val_frames", "log_every",
                   "checkpoint_every")

LOCK_FILE = "run.lock"


class SettingsChanged(UserError):
    """A run folder holds a run made with other settings; the sweep stops rather than mix them."""


def _differences(saved: dict[str, Any], cfg: TrainConfig) -> list[str]:
    now = cfg.to_dict()
    saved = {**TrainConfig().to_dict(), **saved}  # a field a run's record predates has its default
    return [f"{k}: {saved.get(k)!r} there, {v!r} now" for k, v in now.items()
            if k not in _NEUTRAL_FIELDS and saved.get(k) != v]


def _check_same(saved: dict[str, Any], cfg: TrainConfig, where: Path, what: str) -> None:
    diff = _differences(saved, cfg)
    if diff:
        raise SettingsChanged(f"{where}: {what} with other settings ({'; '.join(diff)})",
                              hint="use another --out")


def _check_same_run(result: dict[str, Any], spec: RunSpec, where: Path) -> None:
    """Refuse a finished run made with other passes or another choice of labelled frames than ``spec``."""
    saved = result.get("two_pass"), result.get("data", {}).get("label_choice", "random")
    now = spec.two_pass, spec.label_choice
    if saved != now:
        raise SettingsChanged(f"{where}: finished with {_describe(*saved)}, {_describe(*now)} now",
                              hint="use another --out")


def _describe(two_pass: dict[str, Any] | None, label_choice: str) -> str:
    passes = "one pass" if two_pass is None else "two passes " + json.dumps(two_pass, sort_keys=True)
    return f"{passes} and labelled frames chosen by {label_choice}"


def checkpoint_step(run_dir: Path) -> int:
    """The step of ``run_dir``'s last checkpoint, 0 when there is none or it cannot be read (training then
    decides what to do with it). Read by the checkpoint's own reader: a crafted file runs no code."""
    path = run_dir / CHECKPOINT_FILE
    if not path.is_file():
        return 0
    with contextlib.suppress(UserError, OSError):
        return read_checkpoint_step(path)
    return 0


def run_one(spec: RunSpec, exp_dir: Path, data_dir: Path, opts: Options,
            log: Callable[[str], None] = say) -> dict[str, Any] | None:
    """Train and evaluate one run unless finished; returns its result (None: another process has it).

    Raises:
        SettingsChanged: the run folder holds a run made with other settings (names the fields).
    """
    run_dir = exp_dir / "runs" / spec.name
    result_path = run_dir / RESULT_FILE
    if result_path.is_file():
        result = json.loads(result_path.read_text())
        _check_same(result["config"], spec.cfg, result_path, "finished")
        _check_same_run(result, spec, result_path)
        return result
    run_dir.mkdir(parents=True, exist_ok=True)
    with file_lock(run_dir / LOCK_FILE, blocking=False) as mine:
        if not mine:
            log(f"{spec.name}: being trained by another process; skipped")
            return None
        if result_path.is_file():  # finished by another process meanwhile
            return json.loads(result_path.read_text())
        if RunFolder(run_dir).config_file.is_file():
            _check_same(RunFolder(run_dir).read_record()["config"], spec.cfg, run_dir, "a run is there")
        result = _train_and_evaluate(spec, exp_dir, data_dir, opts, log)
        atomic_write_json(result, result_path)
    m = result["metrics"]["test"]
    mm_2d = m["rms_px"] * m["mm_per_px"] if m.get("rms_px") is not None and m.get("mm_per_px") else None
    log(f"{spec.name}: rms_px {fmt(m['rms_px'])} ({fmt(mm_2d)} mm at {fmt(m.get('mm_per_px'))} mm per px), "
        f"median_mm {fmt(m['median_mm'])}, {result['wall_time_s']['total']:.0f} s")
    return result


def _train_and_evaluate(spec: RunSpec, exp_dir: Path, data_dir: Path, opts: Options,
                        log: Callable[[str], None]) -> dict[str, Any]:
    """The data, training and evaluation of one claimed run; returns its result record."""
    run_dir = exp_dir / "runs" / spec.name
    t0 = time.perf_counter()
    pool_dir, _ = ensure_pool(data_dir, spec.pool, opts.workers, opts.progress, log)
    pool = Dataset.open(pool_dir, cache="none")
    frames = select_frames(pool, spec.labelled, spec.unlabelled, spec.seed, spec.pool.seed, spec.label_choice)
    views = data_dir / "views" / spec.pool.name
    chosen = "" if spec.label_choice == "random" else f"-{spec.label_choice}"
    view = make_view(pool, views / f"L{spec.labelled}{chosen}-s{spec.seed}-U{spec.unlabelled}",
                     {k: v for k, v in frames.items() if len(v)},
                     {"labelled": spec.labelled, "unlabelled": spec.unlabelled, "seed": spec.seed})
    t_data = time.perf_counter() - t0
    start_step = checkpoint_step(RunFolder(run_dir).fine.path if spec.two_pass else run_dir)
    log(f"{spec.name}: training {spec.cfg.schedule.steps} steps "
        f"({'S3K' if spec.cfg.self_supervision.unsup else 'labels only'}, {spec.labelled} labelled, "
        f"{spec.unlabelled} unlabelled, seed {spec.seed}" + (", two passes" if spec.two_pass else "") + ")"
        + (f", resuming at step {start_step}" if start_step else ""))
    t1 = time.perf_counter()
    # each pass of two is resumed where it stopped; a pass that does not finish raises (the run fails)
    trained = train(view, run_dir, spec.train_config(), resume=True)
    status, step = trained.status, trained.step
    timing: dict[str, Any] = (trained.timing if trained.passes is None else
                              {k: p.timing for k, p in trained.passes.items() if p is not None})
    t_train = time.perf_counter() - t1
    t2 = time.perf_counter()
    metrics = {"test": evaluate_run(run_dir, view, "test", device=opts.device)}
    if spec.eval_train:
        # training instances, on frames never labelled: the unlabelled frames every seed shares
        eval_ids = select_frames(pool, 0, min(spec.pool.unlabelled, spec.pool.test), 0,
                                 spec.pool.seed)["unlabelled"]
        train_view = make_view(pool, views / "train-instances-eval", {"test": eval_ids},
                               {"purpose": "evaluation on training instances"})
        metrics["train"] = evaluate_run(run_dir, train_view, "test", device=opts.device)
        drop_cache(train_view)
    t_eval = time.perf_counter() - t2
    drop_cache(view)
    return {
        "experiment": spec.experiment, "run": spec.name, "params": spec.params,
        "status": status, "steps": step, "image_size": metrics["test"]["image_size"],
        "scale": opts.scale,
        "data": {"pool": spec.pool.name, "pool_spec": dataclasses.asdict(spec.pool),
                 "view": os.path.relpath(view, exp_dir), "label_choice": spec.label_choice,
                 "frames": {k: len(v) for k, v in frames.items()}},
        "config": spec.cfg.to_dict(), "two_pass": spec.two_pass, "metrics": metrics,
        "wall_time_s": {"data": t_data, "train": t_train, "evaluate": t_eval,
                        "total": time.perf_counter() - t0},
        "train_timing": timing, "resumed_from_step": start_step,
        "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "host": socket.gethostname(),
        "command": opts.command, "code_revision": source_revision(),
    }


def describe_plan(runs: Sequence[RunSpec], exp_dir: Path, data_dir: Path, scale: str) -> str:
    """What a sweep will do: runs, datasets to render, estimated CPU time."""
    if not runs:
        return f"scale {scale}: no runs"
    pools = {r.pool.name: r.pool for r in runs}
    todo = [r for r in runs if not (exp_dir / "runs" / r.name / RESULT_FILE).is_file()]
    done = len(runs) - len(todo)
    missing = [p for n, p in pools.items() if not (data_dir / n / "s3k.json").is_file()]
    cpu = sum(r.estimated_cpu_s() for r in todo) + sum(p.images() for p in missing) / RENDER_IMAGES_PER_S
    n_base = sum(not r.cfg.self_supervision.unsup for r in runs)
    sizes = sorted({r.pool.size for r in runs})
    steps = sorted({r.cfg.schedule.steps for r in runs})
    t = runs[0].two_pass
    passes = "" if t is None else (f" rendered, two passes (coarse {t['coarse_size']} px for "
                                   f"{t['coarse_steps']} steps, then {t['crop_size']} px crops)")
    return (f"{runs[0].experiment} ({DESCRIPTIONS[runs[0].experiment]}), scale {scale}: {len(runs)} runs "
            f"({n_base} labels-only, {len(runs) - n_base} S3K; {done} already finished), "
            f"{len(pools)} dataset(s) ({len(missing)} to render, "
            f"{sum(p.images() for p in missing)} images), {'/'.join(map(str, sizes))} px{passes}, "
            f"{'/'.join(map(str, steps))} steps; estimated {cpu / 3600:.2f} CPU-hours left "
            f"(one process, one thread per run; about half the wall time with two invocations in parallel)")


def check_pools_fit(runs: list[RunSpec], opts: Options, data_dir: Path) -> None:
    """Refuse, before the sweep starts, a pool that cannot be rendered here (the memory and disk checks of
    ``s3k simulate``): every run reading it would fail. The message names the option that sets its size."""
    from s3k.sim.generate import check_disk, check_memory, default_workers  # heavy: MuJoCo

    workers = opts.workers or default_workers()
    option = "--render" if opts.two_pass and opts.render else "--size"
    for pool in {spec.pool.name: spec.pool for spec in runs}.values():
        if (data_dir / pool.name / "s3k.json").is_file():
            continue
        try:
            check_memory(pool.simulate_config(), workers)
            check_disk(pool.simulate_config(), data_dir)
        except UserError as exc:
            raise UserError(f"{option} {pool.size}: the sweep's pool {pool.name} cannot be rendered here "
                            f"({exc.message}); every run would fail", hint=f"lower {option}, --test or "
                            "--unlabelled") from exc


def run_experiment(opts: Options, log: Callable[[str], None] = say) -> dict[str, Any]:
    """Run every missing run of a sweep, then summarize. Returns ``{"trained", "skipped", "failed",
    "summary"}`` (run names trained now, already finished or held by another process, failed).

    Raises:
        UserError: the options do not make a plan (see :func:`plan`).
        SettingsChanged: a run folder holds a run made with other settings.
    """
    runs = plan(opts)
    exp_dir = opts.out / opts.experiment
    data_dir = opts.out / "data"
    check_pools_fit(runs, opts, data_dir)
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
        except (KeyboardInterrupt, SettingsChanged):
            raise
        except ValueError as exc:
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
