"""`s3k stream`: live 3D keypoints from synchronized cameras, videos or image folders
(:mod:`s3k.inference.stream`); the read-out and filter settings are :class:`s3k.inference.track_config.
TrackConfig`'s (the filter off by default)."""

from __future__ import annotations

import argparse
import sys

from s3k.base.messages import NOTE, note
from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.config_options import add_config_arguments, config_from_args
from s3k.cli.options import add_rig_options, camera_pairs, number, rig_options
from s3k.detector import Detector
from s3k.inference.session import RigSession
from s3k.inference.stream import open_sources, pace_line, rerun_logger, stream_session
from s3k.inference.track_config import TrackConfig

STREAM = TrackConfig.from_flat(filter="none")
"""The settings ``s3k stream`` starts from: live points are not filtered unless asked."""


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Stream 3D keypoints from synchronized sources of a calibrated rig with a trained "
                          "detector: one JSON line per frame on stdout (frame, time, points, valid, "
                          "latency_ms), the frames per second on stderr at the end.")
    parser.epilog = examples(
        "s3k stream runs/box --calibration calibration.toml --sources back=0 mid=1 side=2 top=3 --rerun",
        "s3k stream runs/box --calibration calibration.toml --sources back=back.mp4 mid=mid.mp4 "
        "side=side.mp4 top=top.mp4 --max-frames 100 > points.jsonl",
        "s3k stream runs/box --calibration calibration.toml --sources back=0 mid=1 side=2 top=3 "
        "--filter kalman")
    parser.add_argument("run", help="run folder written by 's3k train' (one pass or --two-pass)")
    parser.add_argument("--sources", nargs="+", required=True, metavar="CAM=SOURCE",
                        help="one source per camera: a camera index (0) or device (/dev/video2), a video "
                        "file, an image folder or pattern; camera names as in the calibration")
    parser.add_argument("--max-frames", type=number(int, ge=1), default=None,
                        help="stop after this many frames (default: until a source ends, or Ctrl-C)")
    parser.add_argument("--rerun", nargs="?", const="spawn", default=None, metavar="FILE.rrd",
                        help="log the cameras, views, detections, 3D points with their skeleton and "
                        "confidence to a Rerun viewer (spawned), or to a .rrd file given here (needs "
                        "rerun-sdk; default: off)")
    parser.add_argument("--image-scale", type=number(float, gt=0, le=1), default=0.5,
                        help="--rerun: size of the logged views relative to the sources' (default "
                        "%(default)s)")
    parser.add_argument("--jpeg-quality", type=number(int, ge=1, le=100), default=75,
                        help="--rerun: JPEG quality of the logged views (default %(default)s)")
    parser.add_argument("--fps", type=number(gt=0), default=None,
                        help="frame rate of sources that record none (image folders and patterns; default: "
                        "unknown)")
    parser.add_argument("--overwrite", action="store_true", help="replace the --rerun file if it exists")
    add_rig_options(parser)
    add_config_arguments(parser, TrackConfig, STREAM, ("filtering", "gates", "limbs", "readout"))


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args, TrackConfig, STREAM).validate()
    specs = camera_pairs(args.sources, "--sources")
    if args.rerun and args.rerun != "spawn":  # a recording file: the output check of every command
        check_output(args.rerun, args.overwrite, option="--rerun", inputs={
            "--calibration": args.calibration, "RUN": args.run, "--sources": list(specs.values())})
    detector = Detector.load(args.run, args.device)
    sources = open_sources(specs, args.fps)
    sizes = {n: s.size for n, s in sources.items()}
    session = RigSession.place(detector, sizes, rig_options(args, list(specs)), "--sources", specs, NOTE)
    log, close = rerun_logger(session, sources, args.rerun, args.image_scale, args.jpeg_quality) \
        if args.rerun else (None, None)
    try:
        summary = stream_session(session, sources, config, sys.stdout, args.max_frames, log)
    except BaseException:  # the recording is kept whole, or not at all
        if close is not None:
            close(False)
        raise
    if close is not None:
        close(True)
    note(pace_line(summary, sources))
    return 0
