"""`s3k evaluate`: a trained detector's metrics on a dataset split, and a report (:mod:`s3k.evaluate`)."""

from __future__ import annotations

import argparse
import json
import sys

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
    parser.add_argument("--overlays", type=int, default=6, help="frames drawn in the report (default: 6)")
    parser.add_argument("--batch-size", type=int, default=16, help="frames per forward pass (default: 16)")
    parser.add_argument("--device", default="auto", help="'auto', 'cpu', 'cuda' (default: auto)")


def _two_pass_pixels(metrics: dict, data: str) -> str:
    """A two-pass run's pixel metrics are in crop pixels: add them in the dataset's image pixels (at the
    workspace centre, where a crop pixel is ``extent / size`` world units); the line that says so."""
    import numpy as np

    from s3k.data import Dataset
    from s3k.evaluate import pixel_sizes_mm

    rule = metrics["two_pass"]
    ds = Dataset.open(data, cache="none")
    image_px = float(np.nanmedian(pixel_sizes_mm(ds.calibration(ds.frames()[:1], np.float64)[0], 1.0)))
    line = (f"rms_px and rms_px_reproj are in pixels of the refining pass's {rule['size']} px crops "
            f"({rule['extent']:g} {ds.units} wide)")
    if not np.isfinite(image_px) or image_px <= 0:
        return line
    k = rule["extent"] / rule["size"] / image_px
    rule["image_px_per_crop_px"] = k
    shown = []
    for name in ("rms_px", "rms_px_reproj"):
        if metrics.get(name) is not None:
            metrics[f"{name}_image"] = metrics[name] * k
            shown.append(f"{name} {metrics[name] * k:.2f}")
    W, H = ds.image_size
    return (f"{line}; a crop pixel is about {k:.2f} px of the dataset's {W}x{H} images at the workspace "
            f"centre: there {', '.join(shown)} px")


def run(args: argparse.Namespace) -> int:
    metrics = evaluate_run(args.run, args.data, args.split, args.device, args.batch_size, args.report,
                           args.overlays)
    units = _two_pass_pixels(metrics, args.data) if "two_pass" in metrics else None
    if args.json:
        print(json.dumps(metrics))
    else:
        print(format_table(metrics))
        if units:
            print(units)
        if args.report:
            print(f"report written to {args.report}", file=sys.stderr)
    return 0
