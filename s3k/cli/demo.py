"""`s3k demo`: command-line front end of :func:`s3k.experiments.demo.run_demo`."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from s3k.cli.options import number
from s3k.experiments.demo import QUICK, DemoConfig, comparison_table, run_demo, schedule_for


def configure_parser(parser: argparse.ArgumentParser) -> None:
    d = DemoConfig()
    parser.add_argument("--out", default="s3k-demo", help="output folder (default: s3k-demo)")
    parser.add_argument("--quick", action="store_true",
                        help="tiny version (under a minute) to check the set-up")
    parser.add_argument("--unlabelled", type=number(int, ge=0), default=None,
                        help=f"unlabelled frames (default {d.unlabelled})")
    parser.add_argument("--test", type=number(int, ge=1), default=None,
                        help=f"test frames (default {d.test})")
    parser.add_argument("--steps", type=number(int, ge=1), default=None,
                        help=f"training steps of the refining pass, or of the one pass (default {d.steps})")
    parser.add_argument("--coarse-steps", type=number(int, ge=1), default=None,
                        help=f"training steps of the coarse pass (default {d.coarse_steps})")
    parser.add_argument("--one-pass", action="store_true",
                        help=f"one network on the whole image at {d.coarse_size} px instead of the "
                             "coarse-to-fine detector")
    parser.add_argument("--warmup-steps", type=number(int, ge=0), default=None,
                        help=f"S3K labels-only warm-up steps (default {d.warmup_steps})")
    parser.add_argument("--alpha", type=number(ge=0), default=None,
                        help=f"S3K alpha after the ramp (default {d.alpha})")
    parser.add_argument("--seed", type=number(int, ge=0), default=d.seed,
                        help=f"dataset and training seed (default {d.seed})")
    parser.add_argument("--sequential", action="store_true",
                        help="train the two models one after the other instead of side by side")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    demo = QUICK if args.quick else DemoConfig()
    over = {k: v for k, v in (("unlabelled", args.unlabelled), ("test", args.test), ("steps", args.steps),
                              ("coarse_steps", args.coarse_steps), ("warmup_steps", args.warmup_steps),
                              ("alpha", args.alpha)) if v is not None}
    demo = replace(demo, seed=args.seed, two_pass=not args.one_pass, **over)
    if args.steps is not None and args.warmup_steps is None:
        schedule = schedule_for(demo.steps)
        demo = replace(demo, warmup_steps=schedule["warmup_steps"], ramp_steps=schedule["ramp_steps"])
    summary = run_demo(args.out, demo, progress=not args.no_progress, parallel=not args.sequential)
    print()
    print(summary["scale"])
    print(comparison_table({k: summary[k] for k in ("labels only", "S3K")}))
    t = summary["timings"]
    total = t.get("total_s", t["this_call_s"])
    print(f"\nreport: {Path(args.out) / 'report'} (total {total / 60:.1f} min, "
          f"this call {t['this_call_s'] / 60:.1f} min)")
    return 0
