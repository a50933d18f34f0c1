"""The label curve: a box preset (``--preset``, default box-headline) at 5, 10, 20, 50 and 100 labelled
frames, S3K and labels only, on N seeds; how many labels labels only needs to match S3K at 10.

The headline's way (``benchmarks/time_to_accuracy.py``): for every seed the box scene is rendered once at 384
px with a pool of 100 labelled + 2000 unlabelled + 200 test frames; the labelled frames of every count are
chosen from the pool as the labelling app's *poses in proportion* ranking would (nested: the 10 contain the
5); both models train with ``s3k train --preset PRESET`` (``--parallel`` at a time, one thread each, CPU time
recorded) and are evaluated on the seed's test frames. Each (labels, model, seed) is a job of its own in
``--work``: a job with a result is skipped, a killed training resumes, so the same command continues the
curve (s3k/experiments/label_curve.py has the folder's layout). Every seed is rendered first; the trainings
then run in seed order (seed 0's whole curve first), each free slot taking the next job. The seeds' pools are
named as ``time_to_accuracy.py`` names its renders, so ``--work`` its working folder reuses them.

Writes ``--results``/summary.json (command, revision, machine and CPU flags, per model and label count the
median, RMS and share within 10 mm per seed with mean and spread, the jobs still missing, and the answer)
and ``--results``/label-curve.png; ``--summary-only`` writes them again from the jobs' results (evaluating
runs that finished since, e.g. while their seed trains on) without rendering or training anything. The answer
is printed last, then the summary's head as JSON.

Example::

    python benchmarks/label_curve.py                     # 30 trainings: 15 x (11.4 + 6.2) CPU-minutes
                                                         # by the headline's, about 2.5 h on 2 idle cores
    python benchmarks/label_curve.py --seeds 1           # seed 0's curve first; the same command with
                                                         # --seeds 3 continues it
    python benchmarks/label_curve.py --summary-only      # summary and figure from the results so far
    python benchmarks/label_curve.py --scene plush --unlabelled-arrangements 50 --label-choice random \\
        --preset none --crop-size 128 --steps 4000 --coarse-steps 4000 --train-options \\
        '--rotation-deg 15 --coarse-rotation 180 --sigma 1.0 --outlier-px 6 --pseudo-window 5 \\
        --val-every 500 --precision auto' --work runs/label-curve-plush \\
        --results docs/results/accuracy/label-curve/plush   # the plush headline's configuration
    python benchmarks/label_curve.py --add-curve enc=$P/label-curve-5.json,$P/label-curve-10.json
        # P=docs/results/accuracy/pretrained: another encoder's points, named enc, in the same figure
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info  # noqa: E402
from s3k.base.errors import UserError  # noqa: E402
from s3k.experiments.accuracy import BACKENDS, without_notes  # noqa: E402
from s3k.experiments.label_curve import LABEL_COUNTS, CurveOptions, add_curve, run_curve  # noqa: E402
from s3k.train.presets import PRESETS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def label_counts(text: str) -> tuple[int, ...]:
    try:
        counts = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"label counts separated by commas, e.g. 5,10,20; got {text!r}") \
            from None
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"label counts must be >= 1, got {text!r}")
    return counts


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--labels", type=label_counts, default=LABEL_COUNTS,
                   help="labelled frame counts (default 5,10,20,50,100)")
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    p.add_argument("--preset", default="box-headline", choices=[*PRESETS, "none"],
                   help="the configuration both models train with (default box-headline; none: the options "
                        "below and --train-options only)")
    p.add_argument("--scene", choices=("box", "plush"), default="box")
    p.add_argument("--render", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--unlabelled", type=int, default=2000, help="unlabelled frames (default 2000)")
    p.add_argument("--test", type=int, default=200, help="test frames (default 200)")
    p.add_argument("--label-pool", type=int, default=None, metavar="N",
                   help="labelled frames rendered per seed (default: the largest of --labels)")
    p.add_argument("--label-choice", choices=("random", "coverage", "representative"),
                   default="representative", help="how each count is chosen from the pool (default "
                                                  "representative: the headline's)")
    p.add_argument("--unlabelled-arrangements", type=int, default=0, metavar="N",
                   help="plush: unlabelled frames over N further arrangements too (default 0)")
    p.add_argument("--steps", type=int, default=None,
                   help="refining (or only) pass steps (default: the preset's)")
    p.add_argument("--coarse-steps", type=int, default=None, help="coarse pass steps (default: preset's)")
    p.add_argument("--coarse-size", type=int, default=None, help="coarse pass size (default: preset's)")
    p.add_argument("--crop-size", type=int, default=None, help="refining pass crop size (default: preset's)")
    p.add_argument("--reference", type=int, default=10,
                   help="the label count of S3K that labels only is measured against (default 10)")
    p.add_argument("--train-options", default="", help="more `s3k train` options for both models")
    p.add_argument("--parallel", type=int, default=2, help="trainings at once, one thread each (default 2)")
    p.add_argument("--backend", choices=BACKENDS, default="local",
                   help="where the trainings run: this machine's processes, or tasks on a Ray cluster, as "
                        "many at once as it has CPUs and --parallel allows (default local)")
    p.add_argument("--address", default=None,
                   help="with --backend ray: the cluster to join (default: RAY_ADDRESS, else a local one)")
    p.add_argument("--work", default=None, help="working folder (default runs/label-curve)")
    p.add_argument("--results", default=None,
                   help="folder of summary.json and label-curve.png "
                        "(default docs/results/accuracy/label-curve)")
    p.add_argument("--summary-only", action="store_true",
                   help="write the summary and figure from the jobs' results so far (finished runs "
                        "evaluated); train nothing")
    p.add_argument("--add-curve", metavar="NAME=SUMMARY[,SUMMARY...]", default=None,
                   help="put another configuration's curve (its summary.json, e.g. the same command with "
                        "--train-options '--encoder ...' and other --work/--results; several, at different "
                        "label counts, joined into one curve) beside the one in --results, in its summary "
                        "(added_curves) and figure, named NAME; trains nothing")
    p.add_argument("--notes", default=None,
                   help="text kept in summary.json (left out of the recorded command)")
    args = p.parse_args(argv)
    if args.unlabelled_arrangements and args.scene != "plush":
        p.error("--unlabelled-arrangements: the plush scene only")
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    try:
        opts = CurveOptions.from_preset(
            None if args.preset == "none" else args.preset, labels=args.labels, seeds=args.seeds,
            scene=args.scene, render=args.render,
            unlabelled=args.unlabelled, test=args.test, label_pool=args.label_pool or max(args.labels),
            label_choice=args.label_choice, unlabelled_arrangements=args.unlabelled_arrangements,
            steps=args.steps, coarse_steps=args.coarse_steps, coarse_size=args.coarse_size,
            crop_size=args.crop_size, train_options=args.train_options, parallel=args.parallel,
            backend=args.backend, address=args.address,
            reference=args.reference)
    except ValueError as e:
        p.error(str(e))
    work = Path(args.work or ROOT / "runs" / "label-curve")
    results = Path(args.results or ROOT / "docs" / "results" / "accuracy" / "label-curve")
    command = shlex.join(["python", "benchmarks/label_curve.py",
                          *without_notes(sys.argv[1:] if argv is None else argv)])
    if args.add_curve:
        name, sep, other = args.add_curve.partition("=")
        if not (sep and name and other):
            p.error(f"--add-curve {args.add_curve!r}: give NAME=SUMMARY[,SUMMARY...], e.g. "
                    "efficientnet-lite0=docs/results/accuracy/pretrained/label-curve-10.json")
        try:
            added = add_curve(results, name, [Path(x) for x in other.split(",") if x], command)
        except UserError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"{results / 'summary.json'}: curves beside its own: {', '.join(added['added_curves'])}",
              file=sys.stderr)
        return 0
    summary = run_curve(opts, work, results, command, git_revision(), machine_info(),
                        summary_only=args.summary_only, notes=args.notes)
    for m, per_count in summary["curve"].items():
        for n, e in per_count.items():
            print(f"{m:12s} {n:>4s} labels: median {e['median_mm']['mean']:.2f} mm, RMS "
                  f"{e['rms_mm']['mean']:.2f} mm, within 10 mm {100 * e['pck_10mm']['mean']:.1f}% "
                  f"(seeds {e['seeds']})", file=sys.stderr)
    if summary["missing_jobs"]:
        print(f"{len(summary['missing_jobs'])} jobs without a result yet", file=sys.stderr)
    for job in summary["unfinished_jobs"]:
        done = ", ".join(f"{name} {step}/{steps} steps" for name, (step, steps) in job["steps"].items())
        print(f"unfinished: {job['job']}: {done}; {job['cpu_minutes']:.1f} CPU-minutes so far",
              file=sys.stderr)
    print(summary["answer"], file=sys.stderr)
    print(json.dumps({k: summary[k] for k in ("command", "git_revision", "avx512_bf16", "labels", "seeds",
                                              "jobs_with_results", "reference_labels",
                                              "labels_only_to_match_s3k")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
