"""`s3k evaluate`: a trained detector's metrics on a dataset split, and a report (:mod:`s3k.evaluate`)."""

from __future__ import annotations

import argparse
import json
import sys

from s3k.cli.options import number
from s3k.evaluate import evaluate_run, format_table


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Score a trained detector on a dataset split: rms_px, rms_px_reproj, median_mm, "
                          "rms_mm; keypoints are matched to the dataset's by name.")
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--data", required=True, help="dataset folder")
    parser.add_argument("--split", default="test", choices=["labelled", "unlabelled", "test"],
                        help="split to evaluate (default: test)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    parser.add_argument("--report", metavar="DIR", default=None,
                        help="write metrics.json, plots and view overlays to DIR")
    parser.add_argument("--overlays", type=number(int, ge=0), default=6,
                        help="frames drawn in the report (default: 6)")
    parser.add_argument("--batch-size", type=number(int, ge=1), default=16,
                        help="frames per forward pass (default: 16)")
    parser.add_argument("--device", default="auto", help="'auto', 'cpu', 'cuda' (default: auto)")


def run(args: argparse.Namespace) -> int:
    if args.report:
        from s3k.outputs import check_output_folder

        check_output_folder(args.report, inputs={"RUN": args.run, "--data": args.data}, option="--report")
    metrics = evaluate_run(args.run, args.data, args.split, args.device, args.batch_size, args.report,
                           args.overlays)
    if args.json:
        print(json.dumps(metrics))
    else:
        print(format_table(metrics))
        if args.report:
            print(f"report written to {args.report}", file=sys.stderr)
    return 0
