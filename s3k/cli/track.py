"""`s3k track`: 3D keypoints from synchronized videos of a calibrated rig (:mod:`s3k.inference.track`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from s3k.cli import examples
from s3k.cli.options import (
    add_filter_options,
    add_rig_options,
    check_filter_rigid,
    filter_limbs,
    filter_settings,
    number,
    parse_crops,
)
from s3k.data import video
from s3k.data.rig import check_camera_name
from s3k.data.tracks_csv import write_source
from s3k.detector.geometry_record import track_crops
from s3k.errors import UserError
from s3k.inference.rig_check import check_rig
from s3k.inference.track import empty_result_hint, overlay_file, track_videos
from s3k.outputs import check_folder, check_output, claim_folder


def parse_videos(values: Sequence[str]) -> dict[str, Path]:
    """``["CAM=FILE", ...]`` -> ``{camera: path}`` with errors naming the bad value."""
    out: dict[str, Path] = {}
    for value in values:
        cam, sep, path = value.partition("=")
        if not sep or not cam or not path:
            raise UserError(f"--videos {value!r}: expected CAMERA=FILE")
        if cam in out:
            raise UserError(f"--videos: camera {cam!r} is given twice")
        out[check_camera_name(cam, f"--videos {value!r}")] = Path(path)
    return out


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
        "--out points3d.csv")
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--videos", nargs="+", required=True, metavar="CAM=FILE",
                        help="one video per camera, or an image sequence (a folder, a glob 'dir/*.png' or a "
                        "pattern 'dir/img_%%05d.jpg'), camera names as in the calibration")
    parser.add_argument("--out", required=True, help="CSV file to write")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument("--overlay", default=None, metavar="DIR",
                        help="write DIR/<camera>.mp4 with the reprojected keypoints drawn; DIR is new, empty "
                             "or an earlier overlay folder (default: none)")
    parser.add_argument("--batch", type=number(int, ge=1), default=8,
                        help="frames per forward pass (default 8)")
    parser.add_argument("--start", type=number(int, ge=0), default=0, help="first frame index (default 0)")
    parser.add_argument("--stop", type=number(int, ge=0), default=None,
                        help="frame index to stop before (default: the end of the shortest video)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_rig_options(parser)
    add_filter_options(parser, "kalman")


def keypoint_line(summary, k: int) -> str:
    """A keypoint's line of the summary: how often it was triangulated, its median error, and for the frames
    without a point, why and which option changes it."""
    valid, passing = summary.valid_fraction[k], summary.passing_fraction[k]
    text = f"{100 * valid:.0f}% valid"
    if valid > 0:
        text += f", median error {summary.median_error_px[k]:.2f} px"
    if valid >= 1 or not summary.frames:
        return text
    reasons = []
    few = 1.0 - passing  # frames where fewer than two views pass --min-weight
    if few > 0:
        change = ("lower --min-weight (0 uses every view, weighted)" if summary.min_weight > 0 else
                  "the detector is not confident there: train on more labelled frames like these")
        reasons.append(f"{100 * few:.0f}% of frames have fewer than 2 views with a confidence weight above "
                       f"--min-weight {summary.min_weight:g} ({change})")
    rest = passing - valid  # enough views, but no point
    if rest > 1e-9:
        reasons.append(f"in {100 * rest:.0f}% of frames its views triangulate to no valid point (rays near "
                       "parallel or the point behind a camera: check --calibration, --video-region and "
                       "--crop)")
    return text + "; no point: " + "; ".join(reasons)


def run(args: argparse.Namespace) -> int:
    videos = parse_videos(args.videos)
    check_output(args.out, args.overwrite,
                 inputs={"--calibration": args.calibration, "--videos": list(videos.values())})
    if not args.other_rig:
        check_rig(args.run, list(videos), what="--videos")
    check_filter_rigid(args, args.run)
    if args.overlay:
        check_folder(args.overlay, "folder of overlay videos", option="--overlay",
                     inputs={"--calibration": args.calibration, "--videos": list(videos.values())},
                     writes={overlay_file(args.overlay, c).name for c in videos})
    crops = parse_crops(args.crop, list(videos)) if args.crop else None
    sizes = {cam: video.frame_size(p) for cam, p in videos.items() if video.exists(p)}
    crops, notes = track_crops(args.run, sizes, crops, fit_given=args.fit is not None)
    settings = filter_settings(args)
    limbs = filter_limbs(args)
    for line in notes:
        print(line, file=sys.stderr if line.startswith("warning:") else sys.stdout)
    if args.overlay:
        claim_folder(args.overlay, "folder of overlay videos")
    summary = track_videos(
        args.run, videos, args.calibration, args.out, overlay=args.overlay, batch=args.batch,
        start=args.start, stop=args.stop, min_weight=args.min_weight, fit=args.fit or "pad", crops=crops,
        device=args.device, units=args.units, progress=not args.no_progress, overwrite=args.overwrite,
        video_regions=parse_crops(args.video_region, list(videos), "--video-region", every=False)
        if args.video_region else None, filter_settings=settings, skeleton=limbs,
    )
    _report(args, summary, videos)
    return 0


def _report(args: argparse.Namespace, summary, videos: dict[str, Path]) -> None:
    """Write the sources beside the CSVs and print what was done."""

    details = {"videos": {c: str(p) for c, p in videos.items()}, "start": args.start,
               "doubt": summary.doubt.name if summary.doubt else None}
    if summary.raw is not None:
        write_source(summary.raw, summary.units, details, run=args.run, calibration=args.calibration,
                     fps=summary.fps)
        details.update(raw=summary.raw.name, filter=summary.filter)
    write_source(summary.path, summary.units, details, run=args.run, calibration=args.calibration,
                 fps=summary.fps)
    what = "filtered " if summary.raw is not None else ""
    print(f"wrote {summary.frames} {what}frames to {summary.path} (units: {summary.units})")
    for k, kp in enumerate(summary.keypoints):
        print(f"  {kp}: {keypoint_line(summary, k)}")
    hint = empty_result_hint(summary)
    if hint:
        print(f"warning: {hint}", file=sys.stderr)
    if summary.filter is not None:
        print(f"raw points in {summary.raw}; the filter rejected {summary.filter['rejected']} jump(s) and "
              f"bridged {summary.filter['bridged']} point(s) (ncams 0 in {summary.path.name})")
    if summary.doubt is not None:
        print(f"frames ranked by doubt in {summary.doubt}")
    if args.overlay:
        print(f"overlay videos in {args.overlay}")
