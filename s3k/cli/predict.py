"""`s3k predict`: 3D keypoints of a dataset's frames as CSV (:mod:`s3k.inference.predict`)."""

from __future__ import annotations

import argparse
import sys

from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.options import add_detector_options, add_other_rig_option
from s3k.data import Dataset
from s3k.data.tracks_csv import write_source
from s3k.detector import Detector
from s3k.inference.predict import predict_dataset
from s3k.inference.session import RigSession


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Predict 3D keypoints of a dataset's frames; writes the 3D CSV of 's3k track' "
                          "(anipose's layout, fnum = dataset frame id).")
    parser.epilog = examples("s3k predict runs/box --data data/box --out points3d.csv",
                             "s3k predict runs/box --data data/box --split all --out all-frames.csv")
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--data", required=True, help="dataset folder")
    parser.add_argument("--out", required=True, help="output CSV file (never a file of the dataset)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument("--split", default="test", choices=["labelled", "unlabelled", "test", "all"],
                        help="split to predict: labelled, unlabelled, test, or 'all' (default: test)")
    add_detector_options(parser)
    add_other_rig_option(parser)


def run(args: argparse.Namespace) -> int:
    check_output(args.out, args.overwrite, inputs={"--data": args.data})
    dataset = Dataset.open(args.data, cache="none")
    session = RigSession.on_dataset(Detector.load(args.run, args.device), dataset, args.other_rig)
    summary = predict_dataset(session, args.data, args.out, args.split, args.batch_size,
                              overwrite=args.overwrite)
    write_source(summary.path, session.units, run=args.run, dataset=args.data)
    for text in summary.warnings:
        print(f"warning: {text}", file=sys.stderr)
    print(f"wrote {summary.frames} frames x {len(summary.keypoints)} keypoints to {summary.path}")
    return 0
