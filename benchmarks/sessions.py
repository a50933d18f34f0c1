"""Several recording sessions against one, on a session neither model saw: does the spread of poses, light
and camera placements of three sessions beat one session with the same number of labels?

Four sessions of the box scene are rendered (``s3k simulate box``, ``--size``), each with its own ``--seed``
(object poses, cameras, lighting); one of them (``--moved-session``, default s3) with its cameras drawn from
another rig (``--moved-rig``, default low: "the cameras moved"). Two datasets are built, each a dataset of
sessions (``s3k import --into DATASET --session NAME --dataset DIR``):

- A: sessions s1, s2 and s3 with ``--labelled`` frames each (default 4,3,3: 10 labels in all) and
  ``--unlabelled`` frames each;
- B: session s1 alone with as many labels (10) and as many unlabelled frames (``--unlabelled`` x 3) as A
  holds in all, so that only where the frames come from differs;

both with session s4 added as a held-out session (``--test-sessions s4``: its test frames only). The labelled
frames of a session are its rendered pool's in the labelling app's *poses in proportion* order (nested: A's 4
of s1 are among B's 10). S3K trains on A and on B with one configuration (``--preset``, default box-fast, with
``--steps``/``--coarse-steps`` over it), one training at a time, one thread, for every ``--seeds``; both
models are then evaluated (``s3k evaluate``'s figures, per session) on A's test frames: s1's, s2's and s3's
(which B never saw) and the held-out s4's.

Everything lives in ``--work``: renders ``render/sN``, datasets ``A`` and ``B``, runs ``runs/{A,B}-seedN``
(a killed training resumes, a finished one is skipped) and their evaluations ``runs/{A,B}-seedN-test.json``,
so the same command continues. Writes ``--results``/summary.json (command, revision, machine with CPU flags,
the configuration, per model and seed the held-out session's median, RMS and share within 10 mm and every
session's, the mean over seeds, training CPU minutes, the runs still missing) and prints the table.

Example::

    python benchmarks/sessions.py --work /tmp/sess-bench/work      # 2 trainings of box-fast, 8 CPU-min each
    python benchmarks/sessions.py --seeds 0,1                       # the same with seed 1 too
    python benchmarks/sessions.py --summary-only                    # summary from the runs finished so far
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info  # noqa: E402
from s3k.experiments.accuracy import without_notes  # noqa: E402
from s3k.train.presets import PRESETS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SESSIONS = ("s1", "s2", "s3", "s4")
HELD_OUT = "s4"
FIGURES = ("median_mm", "rms_mm", "pck_10mm", "pck_5mm", "rms_px", "n_3d")
RIGS = ("train", "low", "high", "far", "wide")


def counts(text: str) -> tuple[int, ...]:
    try:
        out = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"numbers separated by commas, got {text!r}") from None
    if min(out) < 0:
        raise argparse.ArgumentTypeError(f"numbers must be >= 0, got {text!r}")
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--labelled", type=counts, default=(4, 3, 3),
                   help="A's labelled frames of s1, s2, s3 (default 4,3,3); B has their sum, of s1")
    p.add_argument("--unlabelled", type=int, default=200,
                   help="A's unlabelled frames per session (default 200); B has three times as many, of s1")
    p.add_argument("--test", type=int, default=100, help="test frames per session (default 100)")
    p.add_argument("--session-seeds", type=counts, default=(0, 1, 2, 3),
                   help="s3k simulate --seed of s1..s4 (default 0,1,2,3)")
    p.add_argument("--moved-session", choices=SESSIONS, default="s3",
                   help="the session whose cameras moved (default s3)")
    p.add_argument("--moved-rig", choices=RIGS, default="low", help="its --rig (default low)")
    p.add_argument("--seeds", type=counts, default=(0,), help="training seeds (default 0)")
    p.add_argument("--preset", default="box-fast", choices=list(PRESETS), help="training preset (default "
                                                                                "box-fast)")
    p.add_argument("--steps", type=int, default=None, help="refining pass steps (default: the preset's)")
    p.add_argument("--coarse-steps", type=int, default=None, help="coarse pass steps (default: the preset's)")
    p.add_argument("--train-options", default="", help="more `s3k train` options for both models")
    p.add_argument("--work", default=None, help="working folder (default runs/sessions)")
    p.add_argument("--results", default=None, help="folder of summary.json (default docs/results/sessions)")
    p.add_argument("--summary-only", action="store_true",
                   help="evaluate the finished runs and write the summary; render and train nothing")
    p.add_argument("--notes", default=None, help="text kept in summary.json (left out of the command)")
    return p


def log(msg: str) -> None:
    print(f"[sessions {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def render(work: Path, args: argparse.Namespace) -> dict[str, Path]:
    """``work/render/sN`` of every session, rendered once (s4: test frames only; s1: B's labels and
    unlabelled frames, a pool A's are chosen from)."""
    from s3k.sim.generate import SimulateConfig, simulate

    out = {}
    for i, name in enumerate(SESSIONS):
        folder = work / "render" / name
        out[name] = folder
        if (folder / "s3k.json").is_file():
            continue
        if name == HELD_OUT:
            labelled, unlabelled = 0, 0
        else:
            labelled = max(sum(args.labelled), 1)
            unlabelled = 3 * args.unlabelled if name == "s1" else args.unlabelled
        rig = args.moved_rig if name == args.moved_session else "train"
        log(f"rendering {name}: seed {args.session_seeds[i]}, rig {rig}, {labelled} labelled, {unlabelled} "
            f"unlabelled, {args.test} test")
        config = SimulateConfig("box", size=args.size, labelled=labelled, unlabelled=unlabelled,
                                test=args.test, seed=args.session_seeds[i], rig=rig)
        simulate(config, folder, workers=1, progress=False, overwrite=True)
    return out


def session_frames(pool_dir: Path, labelled: int, unlabelled: int) -> dict[str, np.ndarray]:
    """The frames of one session in a dataset: ``labelled`` of the pool's in the labelling app's poses in
    proportion order, the first ``unlabelled`` of its unlabelled frames, every test frame."""
    from s3k.data import Dataset
    from s3k.experiments.views import select_frames

    pool = Dataset.open(pool_dir, cache="none")
    frames = select_frames(pool, labelled, 0, 0, choice="representative")
    frames["unlabelled"] = pool.frames("unlabelled")[:unlabelled]
    return frames


def write_session(pool_dir: Path, out: Path, frames: dict[str, np.ndarray], session: str) -> Path:
    """A new PNG dataset ``out`` of ``frames`` (split -> ids) of ``pool_dir``, every frame in ``session``."""
    from s3k.data import Dataset
    from s3k.data.writer import DatasetWriter

    pool = Dataset.open(pool_dir, cache="none")
    splits = {int(f): split for split, ids in frames.items() for f in np.asarray(ids).tolist()}
    ids = np.asarray([f for f in pool.frames().tolist() if f in splits], dtype=np.int64)
    writer = DatasetWriter(out, pool.keypoints, pool.cameras, pool.image_size, pool.units,
                           per_frame_calibration=not pool.static_calibration, skeleton=pool.skeleton or None,
                           description=pool.description, overwrite=True,
                           source={"session_of": str(pool_dir)},
                           sessions={session: {"source": str(pool_dir)}})
    for start in range(0, len(ids), 64):
        part = ids[start:start + 64]
        pictures = pool.images(part)
        cams = pool.calibration(part, dtype=np.float64)
        uv, mask = pool.labels(part)
        points = pool.points3d(part)
        X = None if points is None else np.where(points[1][..., None], points[0], np.nan)
        for b, frame in enumerate(part.tolist()):
            writer.add_frame(frame, splits[frame], pictures[b], cams[b], labels=(uv[b], mask[b]),
                             points3d=None if X is None else X[b], extra={"session": session})
    return writer.close()


def add_session(into: Path, session: str, part: Path, held_out: bool = False) -> None:
    """``s3k import --into INTO --session SESSION --dataset PART`` (``--test-sessions SESSION`` held out)."""
    cmd = [sys.executable, "-m", "s3k.cli", "import", "--into", str(into), "--session", session,
           "--dataset", str(part), *(["--test-sessions", session] if held_out else [])]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def build_datasets(work: Path, renders: dict[str, Path], args: argparse.Namespace) -> dict[str, Path]:
    """``work/A`` (s1..s3, ``--labelled`` each) and ``work/B`` (s1, their sum), each with s4 held out; built
    in a temporary folder and renamed, so each is complete or absent."""
    plans = {"A": {name: (n, args.unlabelled) for name, n in zip(SESSIONS[:3], args.labelled)},
             "B": {"s1": (sum(args.labelled), 3 * args.unlabelled)}}
    out = {}
    for name, plan in plans.items():
        final = work / name
        out[name] = final
        if (final / "s3k.json").is_file():
            continue
        tmp = work / f"{name}.building"
        shutil.rmtree(tmp, ignore_errors=True)
        parts = work / f"{name}.parts"
        shutil.rmtree(parts, ignore_errors=True)
        for i, (session, (labelled, unlabelled)) in enumerate(plan.items()):
            frames = session_frames(renders[session], labelled, unlabelled)
            if i == 0:
                write_session(renders[session], tmp, frames, session)
            else:
                write_session(renders[session], parts / session, frames, session)
                add_session(tmp, session, parts / session)
        add_session(tmp, HELD_OUT, renders[HELD_OUT], held_out=True)
        shutil.rmtree(parts, ignore_errors=True)
        os.rename(tmp, final)
        log(f"built {final}")
    return out


def train_config(args: argparse.Namespace, seed: int):
    from s3k.train.presets import preset

    cfg = preset(args.preset).replace(seed=seed, threads=1, progress=False)
    if args.steps is not None:
        cfg = cfg.replace(steps=args.steps)
    if args.coarse_steps is not None:
        cfg = cfg.replace(coarse_steps=args.coarse_steps)
    return cfg.with_options(shlex.split(args.train_options), where="--train-options")


def train(data: Path, run: Path, cfg) -> None:
    """``s3k train DATA --out RUN --resume`` with ``cfg``'s options, one thread; skipped when finished."""
    from s3k.run_folder import RunFolder

    if RunFolder(run).is_complete():
        return
    run.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(run), "--resume", *cfg.to_argv()]
    log(f"training {run.name}: {shlex.join(cmd)}")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    with open(run.parent / f"{run.name}.console.txt", "a") as console:
        code = subprocess.run(cmd, stdout=console, stderr=subprocess.STDOUT, env=env).returncode
    if code != 0:
        raise SystemExit(f"training {run.name} failed (exit {code}); see {run.parent / run.name}.console.txt")


def evaluate(run: Path, data: Path) -> dict[str, Any] | None:
    """The run's test figures on ``data`` per session (kept in ``RUN-test.json``); None for an unfinished
    run."""
    from s3k.inference.evaluate import evaluate_run
    from s3k.run_folder import RunFolder

    cache = run.parent / f"{run.name}-test.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    if not RunFolder(run).is_complete():
        return None
    metrics = evaluate_run(run, data, device="cpu")
    cpu = RunFolder(run).read_cpu()
    result = {"all_sessions": {k: metrics[k] for k in FIGURES},
              "sessions": {s: {k: m[k] for k in (*FIGURES, "n_frames")}
                           for s, m in metrics["sessions"].items()},
              "train_cpu_minutes": sum(cpu.values()) / 60 if cpu else None}
    cache.write_text(json.dumps(result, indent=2) + "\n")
    return result


def summarise(results: dict[str, dict[int, dict[str, Any]]]) -> dict[str, Any]:
    """Per model: the mean over seeds of each session's figures, the held-out session's first."""
    out: dict[str, Any] = {}
    for model, per_seed in results.items():
        if not per_seed:
            continue
        sessions = next(iter(per_seed.values()))["sessions"]
        out[model] = {s: {k: float(np.mean([r["sessions"][s][k] for r in per_seed.values()]))
                          for k in ("median_mm", "rms_mm", "pck_10mm")} for s in sessions}
    return out


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if len(args.labelled) != 3 or len(args.session_seeds) != 4:
        p.error("--labelled takes three counts (s1,s2,s3), --session-seeds four (s1..s4)")
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    started = time.perf_counter()
    work = Path(args.work or ROOT / "runs" / "sessions")
    results_dir = Path(args.results or ROOT / "docs" / "results" / "sessions")
    if not args.summary_only:
        renders = render(work, args)
        datasets = build_datasets(work, renders, args)
    else:
        datasets = {"A": work / "A", "B": work / "B"}
    results: dict[str, dict[int, dict[str, Any]]] = {"A": {}, "B": {}}
    missing = []
    for seed in args.seeds:
        for model in ("A", "B"):
            run = work / "runs" / f"{model}-seed{seed}"
            if not args.summary_only:
                train(datasets[model], run, train_config(args, seed))
            r = evaluate(run, datasets["A"])
            if r is None:
                missing.append(run.name)
            else:
                results[model][seed] = r
    mean = summarise(results)
    given = sys.argv[1:] if argv is None else argv
    summary = {
        "command": shlex.join(["python", "benchmarks/sessions.py", *without_notes(given)]),
        "git_revision": git_revision(), "machine": machine_info(),
        "setup": {"scene": "box", "size": args.size, "sessions": {
            "A": {s: n for s, n in zip(SESSIONS, args.labelled)}, "B": {"s1": sum(args.labelled)}},
            "unlabelled": {"A": {s: args.unlabelled for s in SESSIONS[:3]}, "B": {"s1": 3 * args.unlabelled}},
            "test_per_session": args.test, "session_seeds": dict(zip(SESSIONS, args.session_seeds)),
            "moved": {"session": args.moved_session, "rig": args.moved_rig}, "held_out": HELD_OUT,
            "train": train_config(args, 0).to_argv(), "preset": args.preset},
        "held_out": {m: mean[m][HELD_OUT] for m in mean if HELD_OUT in mean[m]},
        "mean_over_seeds": mean,
        "per_seed": results,
        "missing_runs": missing,
        "minutes_this_call": (time.perf_counter() - started) / 60,
        **({"notes": args.notes} if args.notes else {}),
    }
    results_dir.mkdir(parents=True, exist_ok=True)
    from s3k.base.fileio import atomic_write_json

    atomic_write_json(summary, results_dir / "summary.json")
    for model, per_session in mean.items():
        for s, m in per_session.items():
            print(f"{model} ({len(results[model])} seeds) {s}{' (held out)' if s == HELD_OUT else ''}: "
                  f"median {m['median_mm']:.2f} mm, RMS {m['rms_mm']:.2f} mm, within 10 mm "
                  f"{100 * m['pck_10mm']:.1f}%", file=sys.stderr)
    if missing:
        print(f"runs without a result yet: {', '.join(missing)}", file=sys.stderr)
    print(json.dumps({k: summary[k] for k in ("command", "git_revision", "held_out", "missing_runs")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
