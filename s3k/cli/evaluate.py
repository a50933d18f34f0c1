"""`s3k evaluate`: a trained detector's metrics on a dataset split, and a report
(:mod:`s3k.inference.evaluate`)."""

from __future__ import annotations

import argparse
import json
import sys

from s3k.base.label_reference import format_label_reference
from s3k.base.metrics import format_table
from s3k.base.outputs import check_folder, claim_folder
from s3k.cli import examples
from s3k.cli.options import add_detector_options, number
from s3k.detector.geometry_record import check_dataset
from s3k.inference.evaluate import evaluate_run, format_confidence


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Score a trained detector on a dataset split: rms_px, rms_px_reproj, median_mm, "
                          "rms_mm; keypoints are matched to the dataset's by name. Without 3D truth (a real "
                          "recording), the 3D figures are against the labels triangulated from every "
                          "labelled view, with bootstrap 95%% intervals, and the labels' leave-one-view-out "
                          "reprojection error is reported. The confidence follows: the distance its "
                          "calibration counts as right and a reliability table (confidence bins against the "
                          "share of views within it).")
    parser.epilog = examples("s3k evaluate runs/box --data data/box",
                             "s3k evaluate runs/box --data data/box --split labelled --json")
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--data", required=True, help="dataset folder")
    parser.add_argument("--split", default="test", choices=["labelled", "unlabelled", "test"],
                        help="split to evaluate (default: test)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    parser.add_argument("--report", metavar="DIR", default=None,
                        help="write metrics.json, plots and view overlays to DIR, a new or empty folder or "
                             "an earlier report (default: no report)")
    parser.add_argument("--overlays", type=number(int, ge=0), default=6,
                        help="frames drawn in the report (default: 6)")
    add_detector_options(parser)
    parser.add_argument("--ignore-geometry", action="store_true",
                        help="evaluate a dataset whose images show another part of the cameras' frames than "
                             "the run was trained on (refused by default)")


def _two_pass_pixels(metrics: dict) -> str:
    """The line that says a two-pass run's pixel metrics are in crop pixels, with ``rms_px`` in the
    dataset's own image pixels beside them."""
    rule = metrics["two_pass"]
    line = (f"rms_px and rms_px_reproj are in pixels of the refining pass's {rule['size']} px crops "
            f"({rule['extent']:g} world units wide)")
    image = metrics.get("rms_px_image")
    return line if image is None else f"{line}; in the dataset's own images rms_px is {image:.2f} px"


def _earlier_report(folder) -> bool:
    """True when ``folder`` holds only what ``--report`` wrote before its folders were marked: the metrics of
    an evaluation and PNGs."""
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return False
    return (isinstance(metrics, dict) and "rms_px" in metrics and "n_frames" in metrics
            and all(p.name == "metrics.json" or p.suffix == ".png" for p in folder.iterdir()))


def run(args: argparse.Namespace) -> int:
    if not args.ignore_geometry:
        check_dataset(args.run, args.data)
    if args.report:  # a new or empty folder, or an earlier report: never over files s3k did not write
        check_folder(args.report, "report", inputs={"RUN": args.run, "--data": args.data}, option="--report",
                     writes={"metrics.json"}, owns=_earlier_report)
        claim_folder(args.report, "report")
    metrics = evaluate_run(args.run, args.data, args.split, args.device, args.batch_size, args.report,
                           args.overlays)
    units = _two_pass_pixels(metrics) if "two_pass" in metrics else None
    if args.json:
        print(json.dumps(metrics))
    else:
        print(format_table(metrics))
        if metrics.get("labels_3d"):

            print("no 3D truth: median_mm and rms_mm above are against the labels triangulated from every "
                  "labelled view")
            print(format_label_reference(metrics["labels_3d"]))
        if units:
            print(units)
        print(format_confidence(metrics["confidence"]))
        if args.report:
            print(f"report written to {args.report}", file=sys.stderr)
    return 0
