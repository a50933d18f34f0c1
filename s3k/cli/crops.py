"""`s3k crops`: each camera's crop box around the object, found by a run's detector on a dataset of whole
frames, printed as the ``--crop`` arguments of ``s3k import`` (:mod:`s3k.inference.auto_crop`)."""

from __future__ import annotations

import argparse
import json
import math

from s3k.base.fileio import atomic_write_json
from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.options import add_detector_options, add_other_rig_option, number
from s3k.data import Dataset
from s3k.detector import Detector
from s3k.inference.auto_crop import CropOptions, dataset_crop_boxes
from s3k.inference.session import RigSession

DEFAULTS = CropOptions()


def aspect(text: str) -> float | None:
    """``--aspect``: ``W:H`` or a number (width / height), or ``free``."""
    if text == "free":
        return None
    w, sep, h = text.partition(":")
    try:
        value = float(w) / float(h) if sep else float(w)
    except (ValueError, ZeroDivisionError):
        value = math.nan
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected W:H, a positive number or 'free', got {text!r}")
    return value


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Find each camera's crop box around the object: the run's detector (trained briefly on whole "
        "frames; a two-pass run, or its coarse pass RUN/coarse) over the dataset's frames, the box around "
        "the keypoints it places confidently over the frames (a quantile of their extent, not the "
        "largest), grown by a margin, square and of one size for every camera, moved into the frame, in "
        "the full-resolution pixels 's3k import --crop' takes, through the dataset's own import crop and "
        "scale. Every label of the dataset must fall inside its camera's box. Prints the --crop arguments "
        "(notes on standard error), so that the import can take them as they are.")
    parser.epilog = examples(
        "s3k crops runs/whole --data whole",
        "s3k crops runs/whole --data whole --margin 0.3 --out crops.json",
        "s3k crops runs/two-pass/coarse --data whole --aspect 4:3 --outside refuse --json")
    parser.add_argument("run", help="run folder written by 's3k train' (one pass or two)")
    parser.add_argument("--data", required=True, help="the dataset the detector runs on (whole frames)")
    parser.add_argument("--margin", type=number(float, ge=0, le=10), default=DEFAULTS.margin,
                        help="grow each side of the detections' box by this fraction of its width or height "
                             f"(default {DEFAULTS.margin:g})")
    parser.add_argument("--min-margin-px", type=number(float, ge=0), default=DEFAULTS.min_margin_px,
                        metavar="PX", help="and by at least this many full-resolution pixels "
                        f"(default {DEFAULTS.min_margin_px:g})")
    parser.add_argument("--quantile", type=number(float, gt=0.5, le=1), default=DEFAULTS.quantile,
                        help="share of the frames whose keypoints lie inside the box before the margin "
                             f"(1: every frame; default {DEFAULTS.quantile:g})")
    parser.add_argument("--min-confidence", type=number(float, ge=0, lt=1), default=DEFAULTS.min_confidence,
                        help="detections at or below this calibrated confidence are left out "
                             f"(default {DEFAULTS.min_confidence:g})")
    parser.add_argument("--min-keypoints", type=number(float, ge=0, le=1), default=DEFAULTS.min_keypoints,
                        help="a frame's view counts when it keeps at least this share of the keypoints "
                             f"(default {DEFAULTS.min_keypoints:g})")
    parser.add_argument("--aspect", type=aspect, default=DEFAULTS.aspect, metavar="W:H",
                        help="the boxes' width:height, a number, or 'free' for the detections' own shape "
                             "(default 1: square)")
    parser.add_argument("--own-sizes", action="store_true",
                        help="give each camera the size its detections need, instead of the largest one for "
                             "every camera (then import with --size W,H, not --scale)")
    parser.add_argument("--multiple", type=number(int, ge=1), default=DEFAULTS.multiple, metavar="PX",
                        help=f"round the sides up to a multiple of this (default {DEFAULTS.multiple})")
    parser.add_argument("--outside", choices=["grow", "refuse"], default=DEFAULTS.outside,
                        help="a label of the dataset outside its camera's box grows the box, or is refused "
                             "(default: grow; either way the labels are named)")
    parser.add_argument("--split", default="all", choices=["labelled", "unlabelled", "test", "all"],
                        help="the frames to run the detector on (default: all)")
    parser.add_argument("--max-frames", type=number(int, ge=0), default=1000, metavar="N",
                        help="at most this many frames, spread evenly over the split (0: all; default: 1000)")
    parser.add_argument("--session", default=None, help="the frames of this session only (default: all)")
    parser.add_argument("--out", default=None, metavar="FILE.json",
                        help="also write the boxes and how they were found as JSON (default: none)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument("--json", action="store_true", help="print the JSON instead of the --crop arguments")
    add_detector_options(parser)
    add_other_rig_option(parser)


def run(args: argparse.Namespace) -> int:
    if args.out is not None:
        check_output(args.out, args.overwrite, inputs={"--data": args.data, "RUN": args.run})
    dataset = Dataset.open(args.data, cache="none")
    session = RigSession.on_dataset(Detector.load(args.run, args.device), dataset, args.other_rig)
    opts = CropOptions(margin=args.margin, min_margin_px=args.min_margin_px, quantile=args.quantile,
                       min_confidence=args.min_confidence, min_keypoints=args.min_keypoints,
                       aspect=args.aspect, same_size=not args.own_sizes, multiple=args.multiple,
                       outside=args.outside)
    found = dataset_crop_boxes(session.detector, dataset, opts, None if args.split == "all" else args.split,
                               args.max_frames, args.batch_size, args.session)
    doc = {"run": str(args.run), "dataset": str(args.data), **found.to_dict()}
    if args.out is not None:
        atomic_write_json(doc, args.out)
    print(json.dumps(doc, indent=2) if args.json else found.argument())
    return 0
