"""The accuracy benchmark's stages (``benchmarks/accuracy.py``: S3K against the labels-only baseline over
seeds): the rendered datasets and their labelled views, the training commands run a few at a time with their
CPU time recorded, runs reused from an earlier working folder, and the cached test evaluations.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from s3k.base.messages import NOTE
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.experiments.views import make_view, select_frames
from s3k.inference.batch import RETRIES, connect_ray
from s3k.inference.evaluate import evaluate_run
from s3k.run_folder import RunFolder
from s3k.train.presets import preset

log = logging.getLogger(__name__)

FIGURES = ("median_mm", "rms_mm", "pck_5mm", "pck_10mm", "rms_px", "mm_per_px")
MODELS = {"s3k": [], "labels_only": ["--no-unsup"]}
TARGETS = {"median_mm_at_most": 3.0, "rms_mm_at_most": 6.0, "rms_mm_ratio_at_most": 0.6,
           "pck_10mm_at_least": 0.95, "train_cpu_minutes_per_model_at_most": 60.0}


#: Labelled frames every model trains on.
LABELLED = 10


def data_names(args, seed: int) -> list[str]:
    """The folder names of the seed's rendered dataset and, with a larger ``--label-pool``, of the view of it
    that the models train on (the last one is what they train on)."""
    scene = f"{args.scene}{args.render}"
    if getattr(args, "unlabelled_arrangements", 0):
        scene += f"-a{args.unlabelled_arrangements}"
    if args.label_pool == LABELLED:
        return [f"{scene}-seed{seed}"]
    rendered = f"{scene}-L{args.label_pool}"
    return [f"{rendered}-seed{seed}", f"{rendered}-{args.label_choice}-seed{seed}"]


STAGE_TIMES = "stage_times.json"
"""Wall and CPU seconds of each stage that ran in a working folder (``{stage: {"wall_s", "cpu_s"}}``)."""


@contextlib.contextmanager
def timed(work: Path, stage: str):
    """Record the wall time and the CPU time (this process and its finished children) of the block as
    ``stage`` in ``work/stage_times.json``; a block that raises records nothing."""
    def cpu() -> float:
        return sum(u.ru_utime + u.ru_stime for u in (resource.getrusage(resource.RUSAGE_SELF),
                                                    resource.getrusage(resource.RUSAGE_CHILDREN)))

    wall, used = time.perf_counter(), cpu()
    yield
    times = stage_times(work)
    times[stage] = {"wall_s": time.perf_counter() - wall, "cpu_s": cpu() - used}
    (work / STAGE_TIMES).write_text(json.dumps(times, indent=1) + "\n")


def stage_times(work: Path) -> dict[str, dict[str, float]]:
    """What :func:`timed` recorded in ``work`` (empty when nothing was)."""
    try:
        return dict(json.loads((work / STAGE_TIMES).read_text()))
    except (OSError, ValueError):
        return {}


def render(args, seed: int, work: Path) -> Path:
    """The seed's dataset, rendered once (with ``--label-pool`` labelled frames: a view of it with the 10
    chosen by ``--label-choice``); each stage's time is recorded (:func:`timed`)."""
    out = render_pool(args, seed, work)
    if args.label_pool == LABELLED:
        return out
    names = data_names(args, seed)
    if (work / names[1] / "s3k.json").is_file():
        return work / names[1]
    with timed(work, f"label_choice-seed{seed}"):
        return labelled_view(out, work / names[1], args.label_choice, seed)


def render_pool(args, seed: int, work: Path) -> Path:
    """The seed's rendered dataset with all ``--label-pool`` labelled frames, rendered once (its time recorded
    as ``render-seedN``)."""
    pool = args.label_pool
    out = work / data_names(args, seed)[0]
    if not (out / "s3k.json").is_file() and args.scene == "insertion":
        from s3k.robot.insertion_data import write_insertion_dataset

        with timed(work, f"render-seed{seed}"):  # the environment's own rig, episodes drawn by the seed
            write_insertion_dataset(out, labelled=pool, unlabelled=args.unlabelled, test=args.test,
                                    size=args.render, seed=seed, overwrite=True, progress=False)
    elif not (out / "s3k.json").is_file():
        from s3k.sim.generate import SimulateConfig, simulate

        extra: dict[str, Any] = {"mode": "start"} if args.scene == "distractors" else {}
        if getattr(args, "unlabelled_arrangements", 0):
            extra["unlabelled_arrangements"] = args.unlabelled_arrangements
        with timed(work, f"render-seed{seed}"):
            simulate(SimulateConfig(args.scene, size=args.render, labelled=pool, unlabelled=args.unlabelled,
                                    test=args.test, seed=seed, **extra),
                     out, workers=args.parallel, progress=False, overwrite=True)
    return out


def labelled_view(pool_dir: Path, out: Path, choice: str, seed: int, labelled: int = LABELLED) -> Path:
    """A view of the rendered ``pool_dir`` (tables filtered, images linked) with ``labelled`` of its labelled
    frames, chosen by ``choice`` and ``seed``, and all its unlabelled and test frames."""
    if (out / "s3k.json").is_file():
        return out

    pool = Dataset.open(pool_dir, cache="none")
    frames = select_frames(pool, labelled, len(pool.frames("unlabelled")), seed, choice=choice)
    return make_view(pool, out, frames, {"labelled": labelled, "label_choice": choice, "seed": seed})


def reuse_labels_only(source: Path, work: Path, seeds: list[int], args) -> None:
    """Link ``source``'s renders and labels-only runs (with their CPU and test records) into ``work``."""
    for s in seeds:
        run = source / f"labels_only-seed{s}"
        if not finished(run, args.passes):
            raise SystemExit(f"{run}: no finished labels-only run to reuse (--labels-only-from)")
        for name in (*data_names(args, s), run.name, run.name + "-cpu.json", run.name + "-test.json"):
            if (source / name).exists() and not (work / name).exists():
                (work / name).symlink_to((source / name).resolve())


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def reuse_coarse(source: Path, runs: list[Path]) -> None:
    """Start each of ``runs`` not yet begun from the coarse stage of the run of the same name in ``source``:
    its coarse pass and estimates (and crops, where that run wrote them: hard-linked where the file system
    allows), and that stage's CPU minutes in the run's record. ``s3k train --two-pass --resume`` then cuts the
    crops and trains the refining pass, after checking that the coarse pass is what this benchmark's options
    would make."""
    for run in runs:
        if run.exists():
            continue
        src = RunFolder(source / run.name)
        needed = [src.coarse.model, src.estimates, src.cpu]
        missing = [p for p in needed if not p.is_file()]
        if missing or "coarse" not in src.read_cpu():
            raise SystemExit(f"{missing[0] if missing else src.cpu}: no finished coarse stage with its CPU "
                             f"time to reuse (--coarse-from takes runs that record it in {src.cpu.name})")
        tmp = RunFolder(run.with_name(run.name + ".tmp"))
        shutil.rmtree(tmp.path, ignore_errors=True)
        tmp.path.mkdir(parents=True)
        shutil.copytree(src.coarse.path, tmp.coarse.path)
        if (src.crops / "s3k.json").is_file():
            shutil.copytree(src.crops, tmp.crops, copy_function=_link_or_copy)
        shutil.copy2(src.estimates, tmp.estimates)
        coarse_s = src.read_cpu()["coarse"]
        tmp.write_cpu({"coarse": coarse_s})
        record = run.with_name(run.name + "-cpu.json")
        record.write_text(json.dumps({"cpu_minutes": coarse_s / 60, "wall_minutes": 0.0,
                                      "coarse_from": str(src.path)}) + "\n")
        tmp.path.rename(run)


def train_config(args, seed: int, model: str):
    """The :class:`s3k.config.TrainConfig` of one of the benchmark's trainings: ``--preset`` (or the
    defaults), the benchmark's sizes and steps, the model's own options and ``--train-options`` over it."""

    cfg = (preset(args.preset) if getattr(args, "preset", None) else TrainConfig()).replace(
        seed=seed, steps=args.steps, threads=1, progress=False, two_pass=args.passes == 2)
    if args.passes == 2:
        cfg = cfg.replace(coarse_size=args.coarse_size, crop_size=args.crop_size)
        if args.coarse_steps:
            cfg = cfg.replace(coarse_steps=args.coarse_steps)
    else:
        cfg = cfg.replace(image_size=args.coarse_size)
    return cfg.with_options(MODELS[model] + args.train_options.split(), where="--train-options")


def train_command(args, data: Path, run: Path, seed: int, model: str) -> list[str]:
    """The ``s3k train`` command of one training, built from :func:`train_config` (a process of its own, so
    that several run at once and each one's CPU time is measured)."""
    cmd = [sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(run),
           *train_config(args, seed, model).to_argv()]
    if run.exists():
        cmd.append("--resume")
    return cmd


def finished(run: Path, passes: int) -> bool:
    folder = RunFolder(run)
    return folder.is_two_pass() if passes == 2 else folder.model.is_file()


def _cpu_minutes_so_far(pid: int) -> float | None:
    """CPU minutes a running process (and the children it has waited for) has used so far; None without
    Linux's /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    ticks = sum(int(fields[i]) for i in (11, 12, 13, 14))  # user, system, and the waited-for children's
    return ticks / os.sysconf("SC_CLK_TCK") / 60


def read_record(record: Path) -> dict:
    """A training's CPU record, with the minutes of an interrupted attempt (``unfinished_*``) folded in: they
    were spent, whether the run was then resumed or had already finished when its benchmark process died."""
    spent = json.loads(record.read_text()) if record.is_file() else {"cpu_minutes": 0.0, "wall_minutes": 0.0}
    spent["cpu_minutes"] += spent.pop("unfinished_cpu_minutes", 0.0)
    spent["wall_minutes"] += spent.pop("unfinished_wall_minutes", 0.0)
    return spent


BACKENDS = ("local", "ray")
"""Where :func:`run_jobs` runs the trainings: this machine's processes, or tasks on a Ray cluster."""


def run_jobs(jobs: list[tuple[str, list[str], Path]], parallel: int, poll_s: float = 10.0,
             backend: str = "local", address: str | None = None) -> None:
    """Run the training commands ``parallel`` at a time; each one's CPU minutes are added to its record.

    A running job's minutes so far are written to its record every ``poll_s`` seconds as
    ``unfinished_cpu_minutes``, so a run interrupted with this process (a closed session) still counts the
    time it spent when the same command resumes it. ``backend="ray"`` runs each command as a task of one CPU
    on a Ray cluster (:func:`run_jobs_on_ray`)."""
    if backend == "ray":
        run_jobs_on_ray(jobs, parallel, address)
        return
    env = dict(os.environ, OMP_NUM_THREADS="1")
    pending = list(jobs)
    # each job's Popen is kept: a dropped one is reaped by the next Popen's clean-up, and os.wait4 below
    # would then never see it end
    running: dict[int, tuple[str, Path, float, subprocess.Popen]] = {}
    while pending or running:
        while pending and len(running) < parallel:
            name, cmd, record = pending.pop(0)
            spent = read_record(record)
            record.write_text(json.dumps(spent) + "\n")
            log.log(NOTE, f"training {name}")
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, env=env)
            running[proc.pid] = (name, record, time.time(), proc)
        pid, status, usage = os.wait4(-1, os.WNOHANG)
        if pid == 0:
            for job, (_, record, started, _proc) in running.items():
                minutes = _cpu_minutes_so_far(job)
                if minutes is not None:
                    spent = json.loads(record.read_text())
                    spent["unfinished_cpu_minutes"] = minutes
                    spent["unfinished_wall_minutes"] = (time.time() - started) / 60
                    record.write_text(json.dumps(spent) + "\n")
            time.sleep(poll_s)
            continue
        if pid not in running:
            continue
        name, record, started, proc = running.pop(pid)
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by the Popen
        code = os.waitstatus_to_exitcode(status)
        if code != 0:
            raise SystemExit(f"training {name} failed (exit {code}); run the same command again to resume it")
        spent = json.loads(record.read_text())
        spent.pop("unfinished_cpu_minutes", None)
        spent.pop("unfinished_wall_minutes", None)
        spent["cpu_minutes"] += (usage.ru_utime + usage.ru_stime) / 60
        spent["wall_minutes"] += (time.time() - started) / 60
        record.write_text(json.dumps(spent) + "\n")
        log.log(NOTE, f"finished {name}: {spent['cpu_minutes']:.1f} CPU-minutes")


def _die_with_parent() -> None:
    """In a training's process, before it runs: the kernel kills it when the task's worker dies (Linux), so
    that the task's retry is the only training of its run."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _train_job(name: str, cmd: list[str], record: Path) -> float:
    """A Ray task: one training command, one thread; its CPU and wall minutes added to its record."""
    spent = read_record(record)
    record.write_text(json.dumps(spent) + "\n")
    if "--resume" not in cmd and Path(cmd[cmd.index("--out") + 1]).exists():  # an attempt whose worker died
        cmd = [*cmd, "--resume"]
    started = time.time()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, env=dict(os.environ, OMP_NUM_THREADS="1"),
                            preexec_fn=_die_with_parent)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = code = os.waitstatus_to_exitcode(status)  # reaped here, not by the Popen
    if code != 0:
        raise RuntimeError(f"training {name} failed (exit {code})")
    spent["cpu_minutes"] += (usage.ru_utime + usage.ru_stime) / 60
    spent["wall_minutes"] += (time.time() - started) / 60
    record.write_text(json.dumps(spent) + "\n")
    return spent["cpu_minutes"]


def run_jobs_on_ray(jobs: list[tuple[str, list[str], Path]], parallel: int,
                    address: str | None = None) -> None:
    """:func:`run_jobs` on a Ray cluster: each training command a task of one CPU, at most ``parallel`` and
    the cluster's CPUs at once; a task whose worker dies is run again (its ``s3k train`` resumes the run).
    The cluster is the one at ``address`` (or ``RAY_ADDRESS``), else a local one started here. Every node
    must see the data and run folders at the same paths."""
    import ray

    started = connect_ray(parallel, address)
    try:
        limit = max(1, min(parallel, int(ray.cluster_resources().get("CPU", 1))))
        task = ray.remote(num_cpus=1, max_retries=RETRIES)(_train_job)
        pending, running = list(jobs), dict[Any, str]()
        while pending or running:
            while pending and len(running) < limit:
                name, cmd, record = pending.pop(0)
                log.log(NOTE, f"training {name}")
                running[task.remote(name, cmd, record)] = name
            ready, _ = ray.wait(list(running), num_returns=1)
            name = running.pop(ready[0])
            try:
                minutes = ray.get(ready[0])
            except Exception as exc:  # the command failed, or its worker died RETRIES + 1 times
                raise SystemExit(f"training {name} failed ({str(getattr(exc, 'cause', None) or exc)});"
                                 " run the same command again to resume it") from None
            log.log(NOTE, f"finished {name}: {minutes:.1f} CPU-minutes")
    finally:
        if started:
            ray.shutdown()


#: The read-out a cached test evaluation was made with; an evaluation cached by an older read-out (another
#: mark, or none: every view entered the triangulation, each detection the whole heatmap's mean) is made
#: again.
READOUT = ("outlying views left out (each detector's --outlier_px); each detection its heatmap's mean within "
           "6 target widths of its peak; a rigid layout's ties settled by the heatmaps, the coarse pass's "
           "heatmaps in its search")


def evaluate(run: Path, data: Path) -> dict:
    path = run.with_name(run.name + "-test.json")
    if path.is_file():
        metrics = json.loads(path.read_text())
        if metrics.get("readout") == READOUT:
            return metrics

    with timed(run.parent, f"evaluate-{run.name}"):
        metrics = {**evaluate_run(run, data, split="test", device="cpu"), "readout": READOUT}
    path.write_text(json.dumps(metrics, default=float) + "\n")
    return metrics


def seed_stats(values: list[float]) -> dict:
    """A figure over seeds as the benchmarks' summaries keep it: its mean, sample standard deviation (0 for
    one seed) and the values seed by seed."""
    return {"mean": statistics.fmean(values), "sd": statistics.stdev(values) if len(values) > 1 else 0.0,
            "per_seed": values}


def without_notes(argv: list[str]) -> list[str]:
    """``argv`` without ``--notes TEXT`` / ``--notes=TEXT``: a benchmark's recorded command, its notes kept
    apart."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--notes":
            skip = True
        elif not a.startswith("--notes="):
            out.append(a)
    return out


def stage_summary(work: Path, seeds: list[int], runs: dict[tuple[int, str], Path]) -> dict[str, Any]:
    """Minutes per stage, means over ``seeds`` of what ran in ``work``: rendering and the label choice
    (wall and CPU, per seed: :func:`timed`), each model's training stages (CPU, from its run's
    ``cpu.json``: ``coarse``, ``crops``, ``fine``) and its evaluation (wall and CPU). A stage that did not
    run in ``work`` (linked from elsewhere) is left out."""

    times = stage_times(work)

    def mean_of(keys: list[str]) -> dict[str, float] | None:
        found = [times[k] for k in keys if k in times]
        if not found:
            return None
        return {"wall_min": statistics.fmean(t["wall_s"] for t in found) / 60,
                "cpu_min": statistics.fmean(t["cpu_s"] for t in found) / 60, "n": len(found)}

    out: dict[str, Any] = {}
    for stage in ("render", "label_choice"):
        got = mean_of([f"{stage}-seed{s}" for s in seeds])
        if got is not None:
            out[stage] = got
    for model in MODELS:
        per_seed = [RunFolder(runs[s, model]).read_cpu() for s in seeds if (s, model) in runs]
        stages = sorted({k for spent in per_seed for k in spent})
        train = {k: {"cpu_min": statistics.fmean(spent.get(k, 0.0) for spent in per_seed) / 60}
                 for k in stages}
        if train:
            train["total"] = {"cpu_min": sum(v["cpu_min"] for v in train.values())}
            out[f"train_{model}"] = train
        got = mean_of([f"evaluate-{runs[s, model].name}" for s in seeds if (s, model) in runs])
        if got is not None:
            out[f"evaluate_{model}"] = got
    return out
