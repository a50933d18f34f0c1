"""Several recording sessions against one, on sessions neither model saw: does the spread of poses, light
and camera placements of three sessions beat one session with the same number of labels?

Four sessions of the box scene are rendered (``s3k simulate box``, ``--size``), each with its own ``--seed``
(object poses, cameras, lighting); one of them (``--moved-session``, default s3) with its cameras drawn from
another rig (``--moved-rig``, default low: "the cameras moved"). By default every frame draws its own cameras
from its session's rig, so sessions of one rig differ only in their frames' draws; ``--fixed-rigs`` draws
each session's cameras once (``s3k simulate --fixed-rig``), as a lab's rig stays put through a recording:
B then sees one placement of four cameras, A three, and each held-out session another. Two datasets are
built, each a dataset of sessions (``s3k import --into DATASET --session NAME --dataset DIR``):

- A: sessions s1, s2 and s3 with ``--labelled`` frames each (default 4,3,3: 10 labels in all) and
  ``--unlabelled`` frames each;
- B: session s1 alone with as many labels (10) and as many unlabelled frames (``--unlabelled`` x 3) as A
  holds in all, so that only where the frames come from differs;

both with held-out sessions (``--test-sessions``: their test frames only): s4, on the training rig, and one
session per rig no training session used (``--new-rigs``, default high,far,wide: s5, s6, s7, seeds
``--new-rig-seeds``, default 4,5,6). A dataset built before these sessions existed gets them added in place
(``s3k import --into``, all or nothing) once no run on it is unfinished. The labelled frames of a session are
its rendered pool's in the labelling app's *poses in proportion* order (nested: A's 4 of s1 are among B's
10). S3K trains on A and on B with one configuration (``--preset``, default box-fast, with
``--steps``/``--coarse-steps`` over it), one training at a time, one thread, for every ``--seeds``; both
models are then evaluated (``s3k evaluate``'s figures, per session) on A's test frames: s1's, s2's and s3's
(which B never saw) and the held-out sessions'. Per seed and held-out session (and the new-rig sessions
pooled) the paired difference of A's and B's 3D errors on the same points, with a 95% bootstrap interval
over frames; over seeds its mean with a t-interval.

With ``--adapt-steps N``, B (which never saw s3, whose cameras moved) is fine-tuned from its final state for
N steps (``s3k train --init-from``: the run's configuration at its final learning rates, each pass of a
two-pass run), twice: *adapted* on ``B+s3`` (B plus s3's unlabelled frames, no label of s3, so that the
self-supervised term sees the moved cameras) and, as a *control*, on B itself (what training longer alone
does). Per session: B's, adapted's and control's figures and the paired differences adapted - B and
adapted - control. Adaptation should improve s3 and must not make s1 worse.

Everything lives in ``--work``: renders ``render/sN``, datasets ``A``, ``B`` and ``B+s3``, runs
``runs/{A,B}-seedN`` and ``runs/B-seedN-{adapted,control}N`` (a killed training resumes, a finished one is
skipped) and their evaluations ``runs/RUN-test.json`` with the per-point 3D errors ``runs/RUN-test.npz``
(evaluated again only when the dataset has a session they lack), so the same command continues. Writes
``--results``/summary.json (command, revision, machine with CPU flags, the configuration, per model and seed
every session's median, RMS and share within 10 mm, the held-out sessions' (``held_out``: s4's,
``held_out_new_rigs``: per session its rig and both models'), the mean over seeds, the paired differences,
the adaptation, training CPU minutes, the runs still missing) and prints the tables.

Example::

    python benchmarks/sessions.py --work /tmp/sess-bench/work      # 2 trainings of box-fast, 8 CPU-min each
    python benchmarks/sessions.py --seeds 0,1                       # the same with seed 1 too
    python benchmarks/sessions.py --seeds 0,1 --adapt-steps 500 --work /tmp/sess-bench/work   # B adapted
    python benchmarks/sessions.py --summary-only                    # summary from the runs finished so far
    python benchmarks/sessions.py --fixed-rigs --seeds 0,1 --adapt-steps 500 --work /tmp/sess-fixed/work
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

from benchmarks.common import fine_tune_argv, git_revision, machine_info  # noqa: E402
from benchmarks.sessions_results import (  # noqa: E402
    SHOWN,
    differences,
    evaluate,
    log,
    summarise,
    test_sessions,
)
from s3k.experiments.accuracy import without_notes  # noqa: E402
from s3k.train.presets import PRESETS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SESSIONS = ("s1", "s2", "s3", "s4")
HELD_OUT = "s4"
RIGS = ("train", "low", "high", "far", "wide")
POOLED = "new_rigs"


def counts(text: str) -> tuple[int, ...]:
    try:
        out = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"numbers separated by commas, got {text!r}") from None
    if min(out) < 0:
        raise argparse.ArgumentTypeError(f"numbers must be >= 0, got {text!r}")
    return out


def rigs(text: str) -> tuple[str, ...]:
    out = tuple(r for r in text.split(",") if r)
    wrong = [r for r in out if r not in RIGS]
    if wrong or len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f"distinct rigs of {', '.join(RIGS)} separated by commas, got "
                                         f"{text!r}")
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
    p.add_argument("--new-rigs", type=rigs, default=("high", "far", "wide"),
                   help="rigs of the held-out sessions s5, s6, ... beside s4 (default high,far,wide; "
                        "'': none)")
    p.add_argument("--new-rig-seeds", type=counts, default=(4, 5, 6),
                   help="s3k simulate --seed of those sessions, in order (default 4,5,6)")
    p.add_argument("--fixed-rigs", action="store_true",
                   help="each session's cameras drawn once (s3k simulate --fixed-rig), as a lab's rig stays "
                        "put through a recording (default: new cameras every frame, so that sessions of one "
                        "rig differ only in their frames' draws)")
    p.add_argument("--seeds", type=counts, default=(0,), help="training seeds (default 0)")
    p.add_argument("--preset", default="box-fast", choices=list(PRESETS), help="training preset (default "
                                                                                "box-fast)")
    p.add_argument("--steps", type=int, default=None, help="refining pass steps (default: the preset's)")
    p.add_argument("--coarse-steps", type=int, default=None, help="coarse pass steps (default: the preset's)")
    p.add_argument("--train-options", default="", help="more `s3k train` options for both models")
    p.add_argument("--adapt-steps", type=int, default=0,
                   help="fine-tune B this many steps (each pass) on B+s3 (adapted) and on B (control); "
                        "default 0: none")
    p.add_argument("--work", default=None, help="working folder (default runs/sessions)")
    p.add_argument("--results", default=None, help="folder of summary.json (default docs/results/sessions)")
    p.add_argument("--summary-only", action="store_true",
                   help="evaluate the finished runs and write the summary; render and train nothing")
    p.add_argument("--notes", default=None, help="text kept in summary.json (left out of the command)")
    return p


def new_sessions(args: argparse.Namespace) -> dict[str, tuple[str, int]]:
    """The held-out sessions on rigs no training session used: ``{s5: (rig, seed), ...}``."""
    return {f"s{len(SESSIONS) + 1 + i}": (rig, seed)
            for i, (rig, seed) in enumerate(zip(args.new_rigs, args.new_rig_seeds))}


def held_out_sessions(args: argparse.Namespace) -> list[str]:
    """s4 and the new-rig sessions."""
    return [HELD_OUT, *new_sessions(args)]


def render(work: Path, args: argparse.Namespace) -> dict[str, Path]:
    """``work/render/sN`` of every session, rendered once (held-out sessions: test frames only; s1: B's
    labels and unlabelled frames, a pool A's are chosen from)."""
    from s3k.sim.generate import SimulateConfig, simulate

    plans = {name: (args.moved_rig if name == args.moved_session else "train", args.session_seeds[i])
             for i, name in enumerate(SESSIONS)} | new_sessions(args)
    out = {}
    for name, (rig, seed) in plans.items():
        folder = work / "render" / name
        out[name] = folder
        if (folder / "s3k.json").is_file():
            source = json.loads((folder / "s3k.json").read_text()).get("source", {})
            made = (source.get("rig", rig), source.get("seed", seed), source.get("fixed_rig", False))
            if made != (rig, seed, args.fixed_rigs):
                fixed = {True: ", a fixed rig", False: ""}
                raise SystemExit(f"{folder} was rendered with rig {made[0]} and seed {made[1]}"
                                 f"{fixed[made[2]]}, not {rig} and {seed}{fixed[args.fixed_rigs]}: give the "
                                 "options it was made with, or another --work")
            continue
        if name in held_out_sessions(args):
            labelled, unlabelled = 0, 0
        else:
            labelled = max(sum(args.labelled), 1)
            unlabelled = 3 * args.unlabelled if name == "s1" else args.unlabelled
        log(f"rendering {name}: seed {seed}, rig {rig}, {labelled} labelled, {unlabelled} unlabelled, "
            f"{args.test} test")
        config = SimulateConfig("box", size=args.size, labelled=labelled, unlabelled=unlabelled,
                                test=args.test, seed=seed, rig=rig, fixed_rig=args.fixed_rigs)
        simulate(config, folder, workers=1, progress=False, overwrite=True)
    return out


def session_frames(pool_dir: Path, labelled: int, unlabelled: int,
                   test: bool = True) -> dict[str, np.ndarray]:
    """The frames of one session in a dataset: ``labelled`` of the pool's in the labelling app's poses in
    proportion order, the first ``unlabelled`` of its unlabelled frames, every test frame (none without
    ``test``)."""
    from s3k.data import Dataset
    from s3k.experiments.views import select_frames

    pool = Dataset.open(pool_dir, cache="none")
    frames = select_frames(pool, labelled, 0, 0, choice="representative")
    frames["unlabelled"] = pool.frames("unlabelled")[:unlabelled]
    if not test:
        frames["test"] = frames["test"][:0]
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


def plans(args: argparse.Namespace) -> dict[str, dict[str, tuple[int, int, bool]]]:
    """Per dataset, its training sessions' ``(labelled, unlabelled, with test frames)``."""
    b = {"s1": (sum(args.labelled), 3 * args.unlabelled, True)}
    out = {"A": {name: (n, args.unlabelled, True) for name, n in zip(SESSIONS[:3], args.labelled)}, "B": b}
    if args.adapt_steps:
        out[adapted_name(args)] = {**b, args.moved_session: (0, args.unlabelled, False)}
    return out


def adapted_name(args: argparse.Namespace) -> str:
    return f"B+{args.moved_session}"


def runs_on(work: Path, name: str) -> list[Path]:
    """The run folders trained on dataset ``name`` (B's: its fine-tunes too, to be safe)."""
    pattern = {"A": "A-seed*", "B": "B-seed*"}.get(name, "B-seed*-adapted*")
    return sorted(p for p in (work / "runs").glob(pattern) if p.is_dir())


def build_datasets(work: Path, renders: dict[str, Path], args: argparse.Namespace) -> dict[str, Path]:
    """``work/A`` (s1..s3, ``--labelled`` each) and ``work/B`` (s1, their sum), each with the held-out
    sessions, and with ``--adapt-steps`` ``work/B+s3`` (B's s1 and s3's unlabelled frames); built in a
    temporary folder and renamed, so each is complete or absent. A and B built before the new-rig sessions
    existed get them added (:func:`extend`)."""
    out = {}
    for name, plan in plans(args).items():
        final = work / name
        out[name] = final
        extra = held_out_sessions(args) if name in ("A", "B") else []
        if (final / "s3k.json").is_file():
            extend(final, extra, renders, runs_on(work, name))
            continue
        tmp = work / f"{name}.building"
        shutil.rmtree(tmp, ignore_errors=True)
        parts = work / f"{name}.parts"
        shutil.rmtree(parts, ignore_errors=True)
        for i, (session, (labelled, unlabelled, test)) in enumerate(plan.items()):
            frames = session_frames(renders[session], labelled, unlabelled, test)
            if i == 0:
                write_session(renders[session], tmp, frames, session)
            else:
                write_session(renders[session], parts / session, frames, session)
                add_session(tmp, session, parts / session)
        for session in extra:
            add_session(tmp, session, renders[session], held_out=True)
        shutil.rmtree(parts, ignore_errors=True)
        os.rename(tmp, final)
        log(f"built {final}")
    return out


def extend(dataset: Path, sessions: list[str], renders: dict[str, Path], runs: list[Path]) -> None:
    """Add to ``dataset`` in place the held-out ``sessions`` it lacks, one ``s3k import --into`` each (all or
    nothing: the merged dataset is written beside it and takes its place when it reads back). Not while a run
    on it is unfinished: a changed dataset would refuse its ``--resume``."""
    from s3k.data import Dataset
    from s3k.run_folder import RunFolder

    have = Dataset.open(dataset, cache="none").sessions
    todo = [s for s in sessions if s not in have]
    busy = [r.name for r in runs if not RunFolder(r).is_complete()]
    if todo and busy:
        log(f"{dataset.name}: held-out sessions {', '.join(todo)} are added once {', '.join(busy)} finished")
        return
    for session in todo:
        log(f"adding the held-out session {session} to {dataset}")
        add_session(dataset, session, renders[session], held_out=True)


def train_config(args: argparse.Namespace, seed: int):
    from s3k.train.presets import preset

    cfg = preset(args.preset).replace(seed=seed, threads=1, progress=False)
    if args.steps is not None:
        cfg = cfg.replace(steps=args.steps)
    if args.coarse_steps is not None:
        cfg = cfg.replace(coarse_steps=args.coarse_steps)
    return cfg.with_options(shlex.split(args.train_options), where="--train-options")


def run_training(cmd: list[str], run: Path) -> None:
    """``cmd`` (an ``s3k train`` into ``run``), one thread, its output in ``RUN.console.txt``."""
    run.parent.mkdir(parents=True, exist_ok=True)
    log(f"training {run.name}: {shlex.join(cmd)}")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    with open(run.parent / f"{run.name}.console.txt", "a") as console:
        code = subprocess.run(cmd, stdout=console, stderr=subprocess.STDOUT, env=env).returncode
    if code != 0:
        raise SystemExit(f"training {run.name} failed (exit {code}); see {run.parent / run.name}.console.txt")


def train(data: Path, run: Path, cfg) -> None:
    """``s3k train DATA --out RUN --resume`` with ``cfg``'s options, one thread; skipped when finished."""
    from s3k.run_folder import RunFolder

    if not RunFolder(run).is_complete():
        run_training([sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(run), "--resume",
                      *cfg.to_argv()], run)


def fine_tune(data: Path, base: Path, run: Path, steps: int) -> None:
    """``s3k train DATA --out RUN --init-from BASE --steps STEPS`` (BASE's configuration at its final learning
    rates, each pass STEPS), validated on labelled frames; resumed when begun, skipped when finished."""
    from s3k.run_folder import RunFolder

    if RunFolder(run).is_complete():
        return
    run_training(fine_tune_argv(data, base, run, steps), run)


def adaptation_section(args, results, runs: dict[str, dict[int, Path]], sessions: list[str]) -> dict:
    """Per seed and session B's, adapted's and control's figures with the paired differences adapted - B and
    adapted - control (and the differences on the new-rig sessions pooled); over seeds the mean figures and
    the differences' means with t-intervals."""
    models = ("B", "adapted", "control")
    seeds = [seed for seed in args.seeds if all(seed in results[m] for m in models)]
    first = [args.moved_session, "s1"]
    order = [s for s in [*first, *(s for s in sessions if s not in first)]
             if all(s in results[m][seed]["sessions"] for m in models for seed in seeds)]
    new = [s for s in new_sessions(args) if s in order]
    groups = {s: [s] for s in order} | ({POOLED: new} if new else {})
    pick = {m: {seed: runs[m][seed] for seed in seeds} for m in models}
    diffs = {"adapted_minus_B": differences(pick["adapted"], pick["B"], groups),
             "adapted_minus_control": differences(pick["adapted"], pick["control"], groups)}

    def figures(group: str, seeds: list[int]) -> dict[str, Any]:
        if group == POOLED or not seeds:
            return {}
        return {m: {k: float(np.mean([results[m][seed]["sessions"][group][k] for seed in seeds]))
                    for k in SHOWN} for m in models}

    per_seed = {seed: {g: {**figures(g, [seed]),
                           **{d: diffs[d]["per_seed"].get(seed, {}).get(g) for d in diffs}}
                       for g in groups} for seed in seeds}
    over = {g: {**figures(g, seeds), **{d: diffs[d]["over_seeds"][g] for d in diffs}} for g in groups}
    return {"steps": args.adapt_steps, "dataset": adapted_name(args), "adapted_to": args.moved_session,
            "pooled": {POOLED: new}, "seeds": seeds, "per_seed": per_seed, "over_seeds": over}


def interval(d: dict[str, Any], mean: str = "mean_diff_mm", ci: str = "ci95_mm") -> str:
    if d.get(mean) is None:
        return "n/a"
    lo_hi = f" [{d[ci][0]:+.2f}, {d[ci][1]:+.2f}]" if d.get(ci) else ""
    return f"{d[mean]:+.2f}{lo_hi}"


def print_tables(summary: dict[str, Any], results, args) -> None:
    rigs_of = {s: rig for s, (rig, _) in new_sessions(args).items()}
    for model, per_session in summary["mean_over_seeds"].items():
        for s, m in per_session.items():
            note = (" (held out)" if s == HELD_OUT else f" (held out, rig {rigs_of[s]})" if s in rigs_of
                    else "")
            print(f"{model} ({len(results[model])} seeds) {s}{note}: median {m['median_mm']:.2f} mm, RMS "
                  f"{m['rms_mm']:.2f} mm, within 10 mm {100 * m['pck_10mm']:.1f}%", file=sys.stderr)
    for g, d in summary["paired"]["over_seeds"].items():
        seeds = "; ".join(f"seed {seed} {interval(p[g])}"
                          for seed, p in summary["paired"]["per_seed"].items())
        print(f"A - B, 3D error on the same points, {g}: {seeds}; mean over seeds "
              f"{interval(d, 'mean_mm')} mm", file=sys.stderr)
    adaptation = summary.get("adaptation")
    if adaptation:
        print(f"adaptation ({adaptation['steps']} steps, {len(adaptation['seeds'])} seeds), median mm B / "
              "adapted / control, mean differences (mm, t-interval over seeds):", file=sys.stderr)
        for s, d in adaptation["over_seeds"].items():
            figures = " / ".join(f"{d[m]['median_mm']:.2f}" for m in ("B", "adapted", "control") if m in d)
            to = " (adapted to)" if s == adaptation["adapted_to"] else ""
            print(f"  {s}{to}: {figures or '-'}; adapted - B {interval(d['adapted_minus_B'], 'mean_mm')}, "
                  "adapted - control "
                  f"{interval(d['adapted_minus_control'], 'mean_mm')}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if len(args.labelled) != 3 or len(args.session_seeds) != 4:
        p.error("--labelled takes three counts (s1,s2,s3), --session-seeds four (s1..s4)")
    if len(args.new_rig_seeds) < len(args.new_rigs):
        p.error(f"--new-rig-seeds: {len(args.new_rigs)} seeds needed, one per --new-rigs")
    if args.adapt_steps and args.moved_session not in ("s2", "s3"):
        p.error("--adapt-steps adapts B to the moved session, which must be s2 or s3 (B holds s1)")
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    started = time.perf_counter()
    work = Path(args.work or ROOT / "runs" / "sessions")
    results_dir = Path(args.results or ROOT / "docs" / "results" / "sessions")
    runs_dir = work / "runs"
    runs = {m: {seed: runs_dir / f"{m}-seed{seed}" for seed in args.seeds} for m in ("A", "B")}
    if args.adapt_steps:
        for kind in ("adapted", "control"):
            runs[kind] = {seed: runs_dir / f"B-seed{seed}-{kind}{args.adapt_steps}" for seed in args.seeds}
    datasets = {name: work / name for name in ("A", "B", adapted_name(args))}
    if not args.summary_only:
        from s3k.run_folder import RunFolder

        renders = render(work, args)
        datasets = build_datasets(work, renders, args)
        for seed in args.seeds:
            for model in ("A", "B"):
                train(datasets[model], runs[model][seed], train_config(args, seed))
            if args.adapt_steps and RunFolder(runs["B"][seed]).is_complete():
                fine_tune(datasets[adapted_name(args)], runs["B"][seed], runs["adapted"][seed],
                          args.adapt_steps)
                fine_tune(datasets["B"], runs["B"][seed], runs["control"][seed], args.adapt_steps)
        for name in ("A", "B"):  # those a run still training held back
            extend(datasets[name], held_out_sessions(args), renders, runs_on(work, name))
    wanted = test_sessions(datasets["A"])
    results: dict[str, dict[int, dict[str, Any]]] = {m: {} for m in runs}
    missing = []
    for model, per_seed in runs.items():
        for seed, run in per_seed.items():
            r = evaluate(run, datasets["A"], wanted)
            if r is None:
                missing.append(run.name)
            else:
                results[model][seed] = r
    mean = summarise(results)
    new = {s: s for s in new_sessions(args)}
    held = [s for s in held_out_sessions(args) if s in wanted]
    groups = {s: [s] for s in held} | ({POOLED: [s for s in new if s in wanted]} if set(new) & wanted else {})
    given = sys.argv[1:] if argv is None else argv
    summary = {
        "command": shlex.join(["python", "benchmarks/sessions.py", *without_notes(given)]),
        "git_revision": git_revision(), "machine": machine_info(),
        "setup": {"scene": "box", "size": args.size, "sessions": {
            "A": {s: n for s, n in zip(SESSIONS, args.labelled)}, "B": {"s1": sum(args.labelled)}},
            "unlabelled": {"A": {s: args.unlabelled for s in SESSIONS[:3]}, "B": {"s1": 3 * args.unlabelled}},
            "test_per_session": args.test, "session_seeds": dict(zip(SESSIONS, args.session_seeds)),
            "moved": {"session": args.moved_session, "rig": args.moved_rig}, "held_out": HELD_OUT,
            "new_rigs": {s: {"rig": rig, "seed": seed} for s, (rig, seed) in new_sessions(args).items()},
            "adapt_steps": args.adapt_steps, "fixed_rigs": args.fixed_rigs,
            "train": train_config(args, 0).to_argv(), "preset": args.preset},
        "held_out": {m: mean[m][HELD_OUT] for m in ("A", "B") if HELD_OUT in mean.get(m, {})},
        "held_out_new_rigs": {s: {"rig": rig, **{m: mean[m][s] for m in ("A", "B") if s in mean.get(m, {})}}
                              for s, (rig, _) in new_sessions(args).items() if s in wanted},
        "paired": {"what": "A's minus B's 3D error (mm) on the same test points; 95% bootstrap interval over "
                           "frames per seed, t-interval over seeds",
                   "pooled": {POOLED: groups.get(POOLED, [])},
                   **differences(runs["A"], runs["B"], groups)},
        "mean_over_seeds": mean,
        "per_seed": results,
        "missing_runs": missing,
        "minutes_this_call": (time.perf_counter() - started) / 60,
        **({"notes": args.notes} if args.notes else {}),
    }
    if args.adapt_steps:
        summary["adaptation"] = adaptation_section(args, results, runs, sorted(wanted))
    results_dir.mkdir(parents=True, exist_ok=True)
    from s3k.base.fileio import atomic_write_json

    atomic_write_json(summary, results_dir / "summary.json")
    print_tables(summary, results, args)
    if missing:
        print(f"runs without a result yet: {', '.join(missing)}", file=sys.stderr)
    print(json.dumps({k: summary[k] for k in ("command", "git_revision", "held_out", "missing_runs")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
