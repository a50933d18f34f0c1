"""`s3k export-labels`: a dataset's 2D labels for DeepLabCut, Lightning Pose, SLEAP or NWB
(:func:`s3k.data.formats.label_export.export_labels`)."""

from __future__ import annotations

import argparse

from s3k.cli import examples
from s3k.data.formats.label_export import FORMATS, export_labels


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Write a dataset's 2D labels in another tool's format: dlc (labeled-data/<camera>/CollectedData_"
        "<scorer>.csv with the images), lightning-pose (CollectedData_<camera>.csv per view, images under "
        "labeled-data/), sleap (one .slp project, a video per camera) or nwb (ndx-pose training frames)."
    )
    parser.epilog = examples("s3k export-labels data/box --format dlc --out dlc-labels",
                             "s3k export-labels data/box --format sleap --split labelled --out labels.slp")
    parser.add_argument("dataset", help="dataset folder")
    parser.add_argument("--format", required=True, choices=FORMATS, help="the other tool's format")
    parser.add_argument("--out", required=True,
                        help="folder for dlc / lightning-pose; FILE.slp for sleap; FILE.nwb for nwb")
    parser.add_argument("--split", nargs="+", default=None, choices=["labelled", "test", "unlabelled"],
                        help="splits whose labels to write (default: all)")
    parser.add_argument("--scorer", default="s3k",
                        help="annotator name in DLC / Lightning Pose CSVs (default: %(default)s)")
    parser.add_argument("--no-images", action="store_true",
                        help="dlc / lightning-pose: write the CSVs only, not the labelled images")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")


def run(args: argparse.Namespace) -> int:
    written = export_labels(args.dataset, args.format, args.out, splits=args.split, scorer=args.scorer,
                            images=not args.no_images, overwrite=args.overwrite)
    for path in written:
        print(f"wrote {path}")
    return 0
