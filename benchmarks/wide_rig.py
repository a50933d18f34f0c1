"""Training on a wider camera rig: one S3K model of a box preset (``--preset``, default box-headline) trained
on data whose cameras are drawn from other ranges than the scene's (``--elevation``, ``--distance``: those of
``s3k simulate``), everything else as the headline's (``benchmarks/time_to_accuracy.py``: the box at 384 px,
a pool of 100 labelled + 2000 unlabelled + 200 test frames from seed ``--seed``, 10 labelled chosen
*representative*, ``s3k train --preset PRESET`` with one thread, its CPU time recorded).

The run is evaluated on its own test frames and, with ``--headline-data``, on the headline's test frames
(the scene's rig), beside ``--compare`` (the headline's run of the same seed, trained on the scene's rig) on
the same frames: what the wider rig costs in range. The test sets outside the rigs are
``benchmarks/outside_rig.py RUN --elevation LO,HI`` (the rigs outside the wider one, and with ``--rigs-from
scene`` the scene's). Each stage is skipped when its output is there, so the same command resumes a killed
training.

With ``--labels-only`` the headline's other model, the same network without the self-supervised term, is
trained on the same data too (``--parallel`` trainings at a time) and read beside it, and
``--compare-labels-only`` reads the headline's labels-only run of the same seed: whether S3K stays ahead of
labels only on the wider rig.

Writes ``--out`` (command, revision, machine and CPU flags, the rig, the trainings' CPU minutes, and per
test set each run's median, RMS and shares within 5 and 10 mm). The table is printed, then the JSON.

Example::

    python benchmarks/wide_rig.py --elevation 10,85 --work runs/wide-rig \\
        --headline-data runs/time-to-accuracy/box384-L100-seed0 \\
        --compare runs/time-to-accuracy/s3k-seed0 \\
        --out docs/results/accuracy/outside-rig/wide-rig-el10-85.json
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import types
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402
from s3k.cli.simulate import number_pair  # noqa: E402
from s3k.experiments.accuracy import (  # noqa: E402
    evaluate,
    finished,
    labelled_view,
    read_record,
    run_jobs,
    timed,
    train_command,
    without_notes,
)
from s3k.experiments.outside_rig import FIGURES, test_set_name  # noqa: E402
from s3k.inference.evaluate import evaluate_run  # noqa: E402
from s3k.sim.rigs import describe_rig, ranged_sampler  # noqa: E402
from s3k.sim.scenes import SCENES  # noqa: E402
from s3k.train.presets import PRESETS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The headline's data: a pool of 100 labelled frames, 10 of them chosen as the labelling app would.
POOL, CHOICE = 100, "representative"


def figures(metrics: dict) -> dict[str, float]:
    return {k: float(metrics[k]) for k in FIGURES} | {"frames": int(metrics["n_frames"])}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--elevation", type=number_pair, default=None, metavar="LO,HI",
                   help="the training cameras' elevations in degrees (default the scene's)")
    p.add_argument("--distance", type=number_pair, default=None, metavar="LO,HI",
                   help="the training cameras' distances in metres (default the scene's)")
    p.add_argument("--preset", default="box-headline", choices=[n for n in PRESETS if n.startswith("box-")],
                   help="the training configuration (default box-headline)")
    p.add_argument("--seed", type=int, default=0, help="sampling and training seed (default 0)")
    p.add_argument("--size", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--unlabelled", type=int, default=2000, help="unlabelled frames (default 2000)")
    p.add_argument("--test", type=int, default=200, help="test frames (default 200)")
    p.add_argument("--headline-data", default=None,
                   help="the headline's rendered pool of the same seed (its test frames: the scene's rig)")
    p.add_argument("--compare", default=None, help="the headline's S3K run of the same seed")
    p.add_argument("--labels-only", action="store_true",
                   help="also train the labels-only model on the same data (the headline's other model)")
    p.add_argument("--compare-labels-only", default=None,
                   help="the headline's labels-only run of the same seed (with --labels-only)")
    p.add_argument("--parallel", type=int, default=1, help="trainings at a time, one thread each (default 1)")
    p.add_argument("--work", default=None, help="working folder (default runs/wide-rig)")
    p.add_argument("--out", default=None, help="result JSON (default: printed only)")
    p.add_argument("--workers", type=int, default=None, help="rendering processes (default: CPUs available)")
    p.add_argument("--notes", default=None, help="text kept in the result (left out of the recorded command)")
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    from s3k.sim.generate import SimulateConfig, simulate

    try:
        rig = ranged_sampler(SCENES["box"].cameras_sampler, args.elevation, args.distance)
    except ValueError as e:
        p.error(str(e))
    work = Path(args.work or ROOT / "runs" / "wide-rig")
    work.mkdir(parents=True, exist_ok=True)
    name = test_set_name("box", args.size, f"L{POOL}", 0, args.seed, args.elevation, args.distance)
    name = name.replace("-test0", "")
    pool = work / name
    if not (pool / "s3k.json").is_file():
        with timed(work, f"render-seed{args.seed}"):
            simulate(SimulateConfig("box", size=args.size, labelled=POOL, unlabelled=args.unlabelled,
                                    test=args.test, seed=args.seed, elevation=args.elevation,
                                    distance=args.distance), pool, workers=args.workers, progress=False,
                     overwrite=True)
    data = labelled_view(pool, work / f"{name}-{CHOICE}", CHOICE, args.seed)
    chosen = PRESETS[args.preset].config
    two = chosen.passes
    options = types.SimpleNamespace(preset=args.preset, steps=chosen.schedule.steps,
                                    passes=2 if two.two_pass else 1, coarse_size=two.coarse_size,
                                    crop_size=two.crop_size, coarse_steps=two.coarse_steps,
                                    train_options="")
    if args.compare_labels_only and not args.labels_only:
        p.error("--compare-labels-only needs --labels-only")
    run = work / f"s3k-{name}"
    runs = {"this run": run}
    if args.labels_only:
        runs["labels only"] = work / f"labels_only-{name}"
    records = {who: r.with_name(r.name + "-cpu.json") for who, r in runs.items()}
    model = {"this run": "s3k", "labels only": "labels_only"}
    run_jobs([(r.name, train_command(options, data, r, args.seed, model[who]), records[who])
              for who, r in runs.items() if not finished(r, options.passes)], args.parallel)
    own = {who: figures(evaluate(r, data)) for who, r in runs.items()}
    sets: dict[str, dict[str, Any]] = {"own test frames (the wider rig)": own}
    compare = {"compared run": args.compare, "compared labels only": args.compare_labels_only}
    if args.headline_data:  # not evaluate(): it caches one evaluation per run, of the run's own data
        headline = Path(args.headline_data)
        row: dict[str, Any] = {who: figures(evaluate_run(r, headline, split="test", device="cpu"))
                               for who, r in runs.items()}
        for who, other in compare.items():
            if other:
                row[who] = figures(evaluate_run(Path(other), headline, split="test", device="cpu"))
        if args.compare:
            row["median_ratio_to_compared"] = row["this run"]["median_mm"] / row["compared run"]["median_mm"]
        sets["headline test frames (the scene's rig)"] = row
    result = {"command": shlex.join(["python", "benchmarks/wide_rig.py",
                                     *without_notes(sys.argv[1:] if argv is None else argv)]),
              "git_revision": git_revision(), "run": str(run.resolve()), "data": str(data.resolve()),
              "preset": args.preset, "seed": args.seed, "training_rig": describe_rig(rig),
              "scene_rig": describe_rig(SCENES["box"].cameras_sampler),
              "compared_run": str(Path(args.compare).resolve()) if args.compare else None,
              "train_cpu_minutes": read_record(records["this run"])["cpu_minutes"], "test_sets": sets}
    if args.labels_only:
        result["labels_only_run"] = str(runs["labels only"].resolve())
        result["labels_only_train_cpu_minutes"] = read_record(records["labels only"])["cpu_minutes"]
        if args.compare_labels_only:
            result["compared_labels_only_run"] = str(Path(args.compare_labels_only).resolve())
    machine = machine_info()
    result["machine"] = machine
    result["avx512_bf16"] = "avx512_bf16" in machine["cpu_flags"]
    if args.notes:
        result["notes"] = args.notes
    for label, row in sets.items():
        for who in ("this run", "labels only", "compared run", "compared labels only"):
            if who in row:
                f = row[who]
                print(f"{label:40s} {who:20s} median {f['median_mm']:.2f} mm, RMS {f['rms_mm']:.2f} mm, "
                      f"within 10 mm {100 * f['pck_10mm']:.1f}%", file=sys.stderr)
    print(f"training: {result['train_cpu_minutes']:.1f} CPU-minutes", file=sys.stderr)
    write_and_emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
