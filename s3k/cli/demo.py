"""`s3k demo`: command-line front end of :func:`s3k.experiments.demo.run_demo`."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from s3k.cli import examples
from s3k.cli.options import number
from s3k.experiments.demo import QUICK, DemoConfig, comparison_table, run_demo
from s3k.train.presets import PRESETS


def configure_parser(parser: argparse.ArgumentParser) -> None:
    d = DemoConfig()
    parser.description = (
        "Render the box scene, train S3K and the labels-only baseline on the same 10 labels with the "
        f"recommended configuration (s3k train --preset {d.preset}), evaluate both on the test frames and "
        "write a report with a picture (OUT/report/demo.png).")
    parser.epilog = examples("s3k demo", "s3k demo --quick --out /tmp/s3k-quick",
                             "s3k demo --preset box-headline --out s3k-demo-headline")
    parser.add_argument("--out", default="s3k-demo",
                        help="output folder: new, empty, or an earlier demo to continue (default: s3k-demo)")
    parser.add_argument("--quick", action="store_true",
                        help="tiny version (about a minute) to check the set-up; its figures mean nothing")
    parser.add_argument("--unlabelled", type=number(int, ge=0), default=None,
                        help=f"unlabelled frames (default {d.unlabelled})")
    parser.add_argument("--test", type=number(int, ge=1), default=None,
                        help=f"test frames (default {d.test})")
    parser.add_argument("--preset", choices=[n for n in PRESETS if PRESETS[n].config.passes.two_pass],
                        default=d.preset,
                        help=f"the configuration both models train with (default {d.preset}; box-headline: "
                             "the headline's, about 1.5x the CPU time per model)")
    parser.add_argument("--seed", type=number(int, ge=0), default=d.seed,
                        help=f"dataset and training seed (default {d.seed})")
    parser.add_argument("--sequential", action="store_true",
                        help="train the two models one after the other instead of side by side")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    demo = QUICK if args.quick else DemoConfig()
    over = {k: v for k, v in (("unlabelled", args.unlabelled), ("test", args.test)) if v is not None}
    demo = replace(demo, seed=args.seed, preset=args.preset, **over)
    summary = run_demo(args.out, demo, progress=not args.no_progress, parallel=not args.sequential)
    print()
    print(summary["scale"])
    print(comparison_table({k: summary[k] for k in ("labels only", "S3K")}))
    t = summary["timings"]
    total = t.get("total_s", t["this_call_s"])
    print(f"\nreport: {Path(args.out) / 'report' / 'demo.png'} and {Path(args.out) / 'report'} (total "
          f"{total / 60:.1f} min, this call {t['this_call_s'] / 60:.1f} min)")
    return 0
