"""`s3k track`: 3D keypoints from synchronized videos of a calibrated rig (:func:`s3k.inference.track.track`);
the settings are the fields of :class:`s3k.inference.track_config.TrackConfig`."""

from __future__ import annotations

import argparse
import json

from s3k.base.errors import UserError
from s3k.cli import examples
from s3k.cli.config_options import add_config_arguments, config_from_args
from s3k.cli.options import add_frame_offsets_option, add_rig_options, camera_pairs, rig_options
from s3k.cli.track_batch import add_batch_options, check_no_batch_options, run_batch
from s3k.inference.track import track
from s3k.inference.track_config import TrackConfig


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Track synchronized videos of a calibrated rig to 3D keypoints with a trained detector; writes "
        "anipose's 3D CSV (<kp>_x, _y, _z, _error, _ncams, _score per keypoint, then fnum) in the "
        "calibration's units, filtered over time (the raw points in <stem>.raw.csv, the filter's settings in "
        "<file>.s3k.json), and the frames ranked by doubt in <stem>.doubt.csv (for 's3k add-frames')."
    )
    parser.epilog = examples(
        "s3k track runs/box --videos back=back.mp4 mid=mid.mp4 side=side.mp4 top=top.mp4 "
        "--calibration calibration.toml --out points3d.csv",
        "s3k track runs/box --videos back=back.mp4 mid=mid.mp4 side=side.mp4 top=top.mp4 "
        "--calibration calibration.toml --min-weight 0.5 --overlay overlays --out points3d.csv",
        "s3k track runs/mouse --videos back=back.mp4 mid=mid.mp4 side=side.mp4 top=top.mp4 "
        "--calibration calibration.toml --filter-model acceleration --filter-gate 5 --out points3d.csv",
        "s3k track runs/box --videos back=back.mp4 mid=mid.mp4 --calibration calibration.toml --filter none "
        "--out points3d.csv",
        "s3k track runs/box --videos back=back.mp4 mid=mid.mp4 --calibration calibration.toml --out x.csv "
        "--filter-gate 5 --print-config",
        "s3k track runs/box --manifest sessions.toml --out tracks --workers 4",
        "s3k track runs/box --manifest sessions.toml --out tracks --address head:6379 --chunk-frames 2000")
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--videos", nargs="+", default=None, metavar="CAM=FILE",
                        help="one video per camera, or an image sequence (a folder, a glob 'dir/*.png' or a "
                        "pattern 'dir/img_%%05d.jpg'), camera names as in the calibration")
    parser.add_argument("--out", required=True, help="CSV file to write (with --manifest: the folder of the "
                        "sessions' CSVs)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved settings as JSON (the flat fields) and track nothing")
    add_rig_options(parser, calibration_required=False)
    add_frame_offsets_option(parser)
    add_batch_options(parser)
    add_config_arguments(parser, TrackConfig)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args, TrackConfig).validate()
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=2))
        return 0
    if args.manifest:
        return run_batch(args, config)
    return track_recording(args, config)


def track_recording(args: argparse.Namespace, config: TrackConfig) -> int:
    """One recording: ``--videos`` with ``--calibration`` to ``--out``."""
    check_no_batch_options(args)
    for option, given in (("--videos", args.videos), ("--calibration", args.calibration)):
        if not given:
            raise UserError(f"{option} is required (or give --manifest)")
    videos = camera_pairs(args.videos, "--videos")
    rig = rig_options(args, list(videos))
    track(args.run, videos, rig, args.out, config, args.overwrite)
    return 0
