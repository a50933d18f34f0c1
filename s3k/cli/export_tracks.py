"""`s3k export-tracks`: the 3D CSV of `s3k track` / `s3k predict` as NWB
(:func:`s3k.data.formats.label_export.export_tracks`)."""

from __future__ import annotations

import argparse

from s3k.cli import examples
from s3k.cli.options import name, number


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Write 3D keypoints (the anipose-style CSV of 's3k track' or 's3k predict') as an NWB file: an "
        "ndx-pose MultiCameraPoseEstimation with one series (x, y, z, confidence) per keypoint."
    )
    parser.epilog = examples("s3k export-tracks points3d.csv --format nwb --out tracks.nwb",
                             "s3k export-tracks points3d.csv --format nwb --out tracks.nwb --fps 100 "
                             "--calibration calibration.toml")
    parser.add_argument("csv", help="3D keypoints CSV")
    parser.add_argument("--format", required=True, choices=["nwb"], help="output format")
    parser.add_argument("--out", required=True, help="FILE.nwb to write")
    parser.add_argument("--fps", type=number(gt=0), default=None,
                        help="frame rate of the videos; timestamps are fnum / fps seconds (default: the rate "
                        "'s3k track' wrote beside the CSV in CSV.s3k.json; refused when none says)")
    parser.add_argument("--calibration", default=None,
                        help="anipose calibration.toml of the rig (stored as calibrated cameras; gives the "
                             "unit; default: none)")
    parser.add_argument("--units", type=name, default=None,
                        help="world length unit (default: the calibration's, else the one 's3k track' or "
                             "'s3k predict' wrote beside the CSV in CSV.s3k.json; refused when none says)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing file")


def run(args: argparse.Namespace) -> int:
    from s3k.data.formats.label_export import export_tracks

    path, units = export_tracks(args.csv, args.format, args.out, fps=args.fps, calibration=args.calibration,
                                units=args.units, overwrite=args.overwrite)
    print(f"wrote {path} (units {units})")
    return 0
