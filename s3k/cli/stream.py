"""`s3k stream`: live 3D keypoints from synchronized cameras, videos or image folders
(:mod:`s3k.inference.stream`)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from s3k.cli import examples
from s3k.cli.options import (
    add_filter_options,
    add_rig_options,
    camera_pairs,
    check_filter_rigid,
    filter_limbs,
    filter_settings,
    number,
    parse_crops,
)
from s3k.data.formats.calibration_files import read_calibration
from s3k.detector import Detector
from s3k.detector.geometry_record import track_crops
from s3k.errors import UserError
from s3k.inference.rerun_log import recording_summary
from s3k.inference.rig_check import check_rig
from s3k.inference.stream import open_source, rerun_logger, stream
from s3k.inference.track import fit_box, limb_indices, say_calibration
from s3k.inference.track_filter import StreamFilter, layout_shape_of
from s3k.outputs import check_output


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Stream 3D keypoints from synchronized sources of a calibrated rig with a trained detector: one JSON "
        "line per frame on stdout (frame, time, points, valid, latency_ms), the frames per second on stderr "
        "at the end."
    )
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
    add_filter_options(parser, "none")


def _cameras(args: argparse.Namespace, sources: dict, input_size: tuple[int, int]):
    """The calibration's cameras of the sources and each source's box onto the detector's input."""

    names = list(sources)
    calib = read_calibration(args.calibration, units=args.units)
    unknown = [c for c in names if c not in calib.names]
    if unknown:
        raise UserError(f"--sources: camera {', '.join(map(repr, unknown))} is not in the calibration "
                        f"(its cameras are {', '.join(calib.names)})")
    sizes = {c: s.size for c, s in sources.items()}
    calib = calib.with_sizes(sizes)
    if args.video_region:
        regions = parse_crops(args.video_region, names, "--video-region", every=False)
        try:
            calib = calib.with_video_regions(regions)  # type: ignore[arg-type]
        except (KeyError, ValueError) as exc:
            raise UserError(f"--video-region: {exc.args[0]}") from None
    calib = calib.select(names)

    say_calibration(args.run, calib, names, args.calibration)
    crops = parse_crops(args.crop, names) if args.crop else None
    crops, notes = track_crops(args.run, sizes, crops, fit_given=args.fit is not None)
    for line in notes:
        print(line, file=sys.stderr)
    for c, name in enumerate(names):
        calibrated = (int(calib.size[c][0]), int(calib.size[c][1]))
        if tuple(sizes[name]) != calibrated:
            raise UserError(f"--sources {name}: frames of {sizes[name][0]}x{sizes[name][1]} px but the "
                            f"calibration gives {calibrated[0]}x{calibrated[1]}",
                            hint="stream the camera at its calibrated resolution")
    boxes = np.array([crops.get(n, fit_box(sizes[n], input_size, args.fit or "pad")) for n in names],
                     dtype=np.float64)
    return calib.cameras, boxes


def _filter(args: argparse.Namespace, detector, cams):
    """The causal filter of the ``--filter`` options, or None."""

    settings = filter_settings(args)
    if settings.method == "none":
        return None
    limbs = filter_limbs(args)
    limbs = detector.meta.recorded_skeleton() if limbs is None else limbs
    return StreamFilter(settings, len(detector.keypoints), cams.numpy(),
                        layout_shape_of(detector.meta.layout), limb_indices(limbs, detector.keypoints))


def run(args: argparse.Namespace) -> int:
    specs = camera_pairs(args.sources, "--sources")
    if len(specs) < 2:
        raise UserError(f"--sources: triangulation needs at least 2 cameras, got {len(specs)}")
    if not args.other_rig:
        check_rig(args.run, list(specs), what="--sources")
    check_filter_rigid(args, args.run)
    if args.rerun and args.rerun != "spawn":  # a recording file: the output check of every command
        check_output(args.rerun, args.overwrite, option="--rerun",
                     inputs={"--calibration": args.calibration, "RUN": args.run,
                             "--sources": list(specs.values())})
    detector = Detector.load(args.run, args.device)
    sources = {name: open_source(spec) for name, spec in specs.items()}
    if args.fps:
        for source in sources.values():
            source.fps = source.fps or float(args.fps)
    cams, boxes = _cameras(args, sources, detector.input_size)
    filt = _filter(args, detector, cams)
    log, close = None, None
    if args.rerun:
        log, close = rerun_logger(detector, list(sources), cams, [s.size for s in sources.values()],
                                  args.rerun, args.image_scale, args.jpeg_quality)
    try:
        summary = stream(detector, sources, cams, boxes, sys.stdout, args.min_weight, args.max_frames, log,
                         filter=filt)
    except BaseException:
        if close is not None:
            close(False)
        raise
    if close is not None:
        close(True)
    if args.rerun and args.rerun != "spawn":

        saved = recording_summary(args.rerun)
        print(f"s3k stream: wrote {args.rerun}: {len(saved['frames'])} frames, {saved['bytes'] / 1e6:.2f} MB "
              f"({saved['bytes_per_frame'] / 1e6:.3f} MB a frame)", file=sys.stderr)
    unknown = [name for name, s in sources.items() if not s.fps]
    pace = (f"; the sources run at {summary.source_fps:g} frames/s" if summary.source_fps else
            f"; the frame rate of {', '.join(unknown)} is unknown (--fps gives it)")
    if summary.behind > 1:
        pace += f", up to {summary.behind} frames behind"
    print(f"s3k stream: {summary.frames} frames in {summary.seconds:.2f} s, {summary.fps:.1f} frames/s{pace}"
          + (" (stopped by Ctrl-C)" if summary.interrupted else ""), file=sys.stderr)
    return 0
