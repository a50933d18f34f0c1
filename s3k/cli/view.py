"""`s3k view`: a dataset, a run's detections or tracks in a Rerun viewer or a .rrd file
(:mod:`s3k.inference.view`)."""

from __future__ import annotations

import argparse

from s3k.base.errors import UserError
from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.options import camera_pairs, device, number
from s3k.inference.rerun_log import recording_summary, rerun_module
from s3k.inference.view import ViewOptions, target_kind, view_dataset, view_run, view_tracks


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Show in Rerun, over time: the cameras (frusta with their images), the 3D keypoints with the "
        "skeleton and each keypoint's confidence, and their 2D reprojections in every view. TARGET is the "
        "3D CSV of 's3k track' (with --videos for the images), a dataset folder (its labels and 3D points), "
        "or a run folder (its detections on --data's --split, beside the ground truth). A viewer is spawned, "
        "or --save writes a .rrd file to open later with 'rerun FILE.rrd'."
    )
    parser.epilog = examples(
        "s3k view points3d.csv --videos back=back.mp4 mid=mid.mp4 side=side.mp4 top=top.mp4 "
        "--calibration calibration.toml",
        "s3k view data/box --split test --save box.rrd",
        "s3k view runs/box --data data/box --split test --max-frames 50")
    parser.add_argument("target",
                        help="3D CSV of 's3k track' / 's3k predict', a dataset folder or a run folder")
    parser.add_argument("--save", default=None, metavar="FILE.rrd",
                        help="write the recording to this file instead of spawning a viewer")
    parser.add_argument("--overwrite", action="store_true", help="replace --save if it exists")
    parser.add_argument("--videos", nargs="+", default=None, metavar="CAM=FILE",
                        help="tracks: the videos (or image sequences) the tracks came from, camera names as "
                        "in the calibration (default: no images)")
    parser.add_argument("--calibration", default=None,
                        help="tracks: the rig's calibration (default: the one 's3k track' recorded beside "
                        "the CSV)")
    parser.add_argument("--units", default=None, help="tracks: world unit when the calibration does not say")
    parser.add_argument("--data", default=None,
                        help="run: the dataset to detect (default: the one it was trained on)")
    parser.add_argument("--split", default=None, choices=["labelled", "unlabelled", "test", "all"],
                        help="dataset / run: the frames to show (default: all for a dataset, test for a run)")
    parser.add_argument("--skeleton", default=None, metavar="FILE",
                        help="take the skeleton from a SLEAP .slp / analysis .h5, a DeepLabCut config.yaml, "
                        "an anipose config.toml or a dataset (default: the dataset's or the run's)")
    parser.add_argument("--start", type=number(int, ge=0), default=0, help="first frame number (default 0)")
    parser.add_argument("--stop", type=number(int, ge=1), default=None,
                        help="frame number to stop before (default: the last)")
    parser.add_argument("--step", type=number(int, ge=1), default=1, help="show every N-th frame (default 1)")
    parser.add_argument("--max-frames", type=number(int, ge=1), default=300,
                        help="show at most this many frames (default %(default)s)")
    parser.add_argument("--image-scale", type=number(float, gt=0, le=1), default=0.5,
                        help="size of the logged images relative to the views (default %(default)s)")
    parser.add_argument("--jpeg-quality", type=number(int, ge=1, le=100), default=75,
                        help="JPEG quality of the logged images (default %(default)s)")
    parser.add_argument("--no-images", action="store_true", help="cameras and keypoints only")
    parser.add_argument("--batch-size", type=number(int, ge=1), default=8,
                        help="run: frames per forward pass (default 8)")
    parser.add_argument("--device", type=device, default="auto",
                        help="run: 'auto', 'cpu', 'cuda' or 'cuda:N' (default: auto)")


def run(args: argparse.Namespace) -> int:
    """``s3k view``: a dataset, a run's evaluation or tracks in Rerun; options that belong to another kind
    of target are refused in one line."""
    rerun_module("s3k view")
    kind = target_kind(args.target)
    videos = camera_pairs(args.videos, "--videos") if args.videos else None
    given = {"--videos": videos, "--calibration": args.calibration, "--units": args.units}
    misplaced = [opt for opt, v in given.items() if v and kind != "tracks"]
    misplaced += [opt for opt, v in {"--data": args.data, "--device": args.device != "auto"}.items()
                  if v and kind != "run"]
    if misplaced:
        raise UserError(f"{misplaced[0]} is for {'tracks' if misplaced[0] in given else 'a run'}; "
                        f"{args.target} is a {kind}")
    if args.split and kind == "tracks":
        raise UserError(f"--split is for a dataset or a run; {args.target} is a 3D CSV")
    if args.save:
        check_output(args.save, args.overwrite, option="--save",
                     inputs={"TARGET": args.target, "--data": args.data, "--calibration": args.calibration,
                             "--videos": list((videos or {}).values())})
    opts = ViewOptions(target=args.save or "spawn", start=args.start, stop=args.stop, step=args.step,
                       max_frames=args.max_frames, image_scale=args.image_scale,
                       jpeg_quality=args.jpeg_quality, images=not args.no_images, skeleton=args.skeleton)
    if kind == "tracks":
        n = view_tracks(args.target, opts, args.calibration, videos, args.units)
    elif kind == "dataset":
        n = view_dataset(args.target, opts, args.split or "all")
    else:
        n = view_run(args.target, opts, args.data, args.split or "test", args.device, args.batch_size)
    if args.save:
        summary = recording_summary(args.save)
        print(f"wrote {args.save}: {n} frames, {summary['bytes'] / 1e6:.2f} MB "
              f"({summary['bytes_per_frame'] / 1e6:.3f} MB a frame); open it with: rerun {args.save}")
    else:
        print(f"sent {n} frames to the Rerun viewer")
    return 0
