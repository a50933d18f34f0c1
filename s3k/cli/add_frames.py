"""`s3k add-frames`: the frames a tracked video was most in doubt about, added to a dataset and queued first
for labelling (:mod:`s3k.label.queue`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from s3k.base.errors import UserError
from s3k.cli import examples
from s3k.cli.options import camera_pairs, number
from s3k.data.tracks_csv import read_source
from s3k.inference.track_filter import doubt_path, read_doubt
from s3k.label.queue import queue_frames


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Take the worst N frames of the doubt ranking 's3k track' wrote beside TRACKS (<stem>.doubt.csv: low "
        "confidence, large reprojection residual, jumps the filter rejected), add those the dataset does not "
        "hold as unlabelled frames cut from the videos as the dataset's images were, and list them first in "
        "DATASET/label-queue.csv for the labelling app. Labelled and test frames are never taken.")
    parser.epilog = examples(
        "s3k add-frames tracked.csv --data data/mouse --worst 10",
        "s3k add-frames tracked.csv --data data/mouse --worst 20 --spacing 5 "
        "--videos back=back.mp4 mid=mid.mp4 side=side.mp4 top=top.mp4")
    parser.add_argument("tracks", help="a 3D CSV written by 's3k track' (its ranking is beside it)")
    parser.add_argument("--data", required=True, help="the dataset to add the frames to")
    parser.add_argument("--worst", type=number(int, ge=1), required=True, metavar="N",
                        help="how many frames to queue")
    parser.add_argument("--spacing", type=number(int, ge=0), default=2, metavar="FRAMES",
                        help="take no frame closer than this to a worse one taken, so that the queue holds "
                             "no near-duplicate neighbours (default 2; 0: any)")
    parser.add_argument("--videos", nargs="+", default=None, metavar="CAM=FILE",
                        help="the videos (default: those 's3k track' recorded beside TRACKS)")


def run(args: argparse.Namespace) -> int:
    """``s3k add-frames``: the worst frames of a track's doubt ranking, from its videos, into the dataset's
    labelling queue."""
    source = read_source(args.tracks) or {}
    if any(source.get("frame_offsets", {}).values()):
        raise UserError(f"{args.tracks}: tracked with --frame-offsets {source['frame_offsets']}; add-frames "
                        "cuts every camera at the same video frame, so it cannot queue this track's frames",
                        hint="import the recording with s3k import --frame-offsets instead")
    named = source.get("doubt")
    ranking = Path(args.tracks).with_name(str(named)) if named else doubt_path(args.tracks)
    rows = read_doubt(ranking)
    if args.videos:
        videos = {c: Path(p) for c, p in camera_pairs(args.videos, "--videos").items()}
    else:
        recorded = source.get("videos")
        videos = {c: Path(p) for c, p in recorded.items()} if isinstance(recorded, dict) else {}
    ranked = [(int(r["fnum"]), float(r["doubt"])) for r in rows]
    if not ranked:
        raise UserError(f"{ranking}: no frame is ranked")
    done = queue_frames(args.data, ranked, args.worst, videos, source=str(args.tracks), spacing=args.spacing)
    print(f"queued {len(done.frames)} frame(s) for labelling in {done.path}, worst first: video frames "
          + ", ".join(str(v) for v in done.video_frames))
    if done.added:
        print(f"added {len(done.added)} of them to {args.data} as unlabelled frames: ids "
              + ", ".join(str(f) for f in done.added))
    if done.skipped:
        print("passed over: " + ", ".join(f"{n} {why}" for why, n in done.skipped.items()))
    return 0
