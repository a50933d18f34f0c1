"""`s3k label`: label keypoints in the browser (:mod:`s3k.label`), and `s3k label propagate`.

``s3k label DATASET [--run RUN]`` serves the app on 127.0.0.1; ``s3k label propagate DATASET --frames A:B
[--from F]`` copies one frame's 3D labels to a still stretch of frames.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from s3k.base.errors import UserError
from s3k.cli import examples
from s3k.cli.options import device, number
from s3k.label.propagate import DEFAULT_MAX_CHANGED, describe, propagate_labels, undo_propagation
from s3k.label.suggest import UP


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Label keypoints in the browser: click a keypoint in two views, s3k triangulates it and shows it in "
        "every view. 's3k label propagate DATASET --frames A:B [--from F]' copies frame F's 3D labels to the "
        "still frames A..B instead.")
    parser.usage = ("s3k label DATASET [--run RUN] [--up X,Y,Z] [--port PORT] [--host HOST] "
                    "[--public-url URL]\n"
                    "       s3k label propagate DATASET --frames A:B [--from F] [--max-changed PERCENT] "
                    "[--dry-run] [--overwrite] [--allow-test]\n"
                    "       s3k label propagate DATASET --undo")
    parser.epilog = examples("s3k label data/session",
                             "s3k label data/session --run runs/session",
                             "s3k label propagate data/plush --frames 0:19 --from 0")
    parser.add_argument("dataset", help="dataset folder (or 'propagate' followed by the dataset folder)")
    parser.add_argument("target", nargs="?", help=argparse.SUPPRESS)
    parser.add_argument("--run", help="a trained run: its predictions are offered as suggestions and the "
                        "unlabelled frames ranked by its multi-view disagreement (default: none)")
    parser.add_argument("--ignore-geometry", action="store_true",
                        help="use --run on a dataset whose images show another part of the cameras' frames "
                             "than the run was trained on (refused by default)")
    parser.add_argument("--port", type=number(int, ge=1, le=65535), default=8765,
                        help="port to serve on (default: 8765)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="interface to serve on (default: 127.0.0.1); any other requires the random "
                             "token in the printed URL")
    parser.add_argument("--public-url", metavar="URL",
                        help="the address a reverse proxy (e.g. nginx with TLS) serves the app at, such as "
                             "https://labels.example.org: pages from there may edit the labels, and a random "
                             "token in the printed URL guards the app (default: none)")
    parser.add_argument("--labeller", help="your name, written into the edit history (default: $USER)")
    parser.add_argument("--device", type=device, default="cpu",
                        help="where --run's detector runs: auto, cpu, cuda or cuda:N (default: cpu)")

    parser.add_argument("--up", default=",".join(f"{c:g}" for c in UP or ()) or "none", metavar="X,Y,Z",
                        help="the table's normal in the calibration's world frame: the pose rankings count a "
                             "pose turned about it as the same pose (default: %(default)s; 'none' counts "
                             "every heading as a pose of its own)")
    group = parser.add_argument_group("propagate")
    group.add_argument("--frames", help="A:B, the frame ids of the still stretch (inclusive; required)")
    group.add_argument("--from", dest="source", type=number(int),
                       help="frame whose labels are copied (default: the "
                       "frame of the stretch with the most keypoints labelled in two or more views)")
    group.add_argument("--max-changed", type=number(ge=0, le=100), default=None,
                       help="largest percentage of a camera's pixels that may differ from the source frame "
                            "by more than 24 grey levels in a still frame (default: 0.2)")
    group.add_argument("--dry-run", action="store_true", help="print what would change, write nothing")
    group.add_argument("--overwrite", action="store_true",
                       help="replace existing labels that differ from the copy (default: refuse)")
    group.add_argument("--allow-test", action="store_true",
                       help="read from and write to test frames (default: refuse; their labels are held "
                            "out for evaluation)")
    group.add_argument("--undo", action="store_true",
                       help="undo the latest propagation (from the label history)")


def _frames(text: str | None) -> tuple[int, int]:
    if not text:
        raise UserError("s3k label propagate needs --frames A:B")
    a, sep, b = text.partition(":")
    try:
        return (int(a), int(b)) if sep else (int(a), int(a))
    except ValueError:
        raise UserError(f"--frames {text!r}: expected A:B with integer frame ids") from None


def _up(text: str) -> tuple[float, float, float] | None:
    """``--up``: three numbers, not all zero, or 'none'."""
    if text.strip().lower() == "none":
        return None
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"--up {text!r}: expected X,Y,Z (e.g. 0,0,1) or 'none'") from None
    if not (all(map(math.isfinite, (x, y, z))) and math.hypot(x, y, z) > 0):
        raise UserError(f"--up {text!r}: the direction must be finite and not zero")
    return (x, y, z)


def run(args: argparse.Namespace) -> int:
    propagate = args.dataset == "propagate" and not Path("propagate", "s3k.json").is_file()
    if propagate and args.target is None:
        raise UserError("s3k label propagate needs the dataset folder",
                        hint="s3k label propagate DATASET --frames A:B")
    if propagate:
        if args.undo:
            source, frames = undo_propagation(args.target, labeller=args.labeller)
            print(f"undid the propagation from frame {source}: frame(s) {', '.join(map(str, frames))} have "
                  "their labels from before it")
            return 0
        first, last = _frames(args.frames)
        result = propagate_labels(args.target, first, last, args.source,
                                  DEFAULT_MAX_CHANGED if args.max_changed is None else args.max_changed,
                                  labeller=args.labeller, overwrite=args.overwrite,
                                  allow_test=args.allow_test, dry_run=args.dry_run)
        print("\n".join(describe(result)))
        if not result.dry_run and result.labels:
            print(f"undo with: s3k label propagate {args.target} --undo")
        return 0
    if args.target is not None:
        raise UserError(f"unexpected argument {args.target!r}; did you mean 's3k label propagate DATASET'?")
    up = _up(args.up)
    for name in ("frames", "source", "max_changed"):
        if getattr(args, name) is not None:
            raise UserError(f"--{name.replace('_', '-')} belongs to 's3k label propagate DATASET'")
    for name in ("dry_run", "overwrite", "allow_test", "undo"):
        if getattr(args, name):
            raise UserError(f"--{name.replace('_', '-')} belongs to 's3k label propagate DATASET'")
    try:
        from s3k.label.server import serve
    except ImportError as exc:
        raise UserError(f"s3k label needs FastAPI and uvicorn ({exc})",
                        hint="pip install 'fastapi>=0.110' 'uvicorn>=0.29'") from None
    serve(args.dataset, args.run, args.host, args.port, args.labeller, args.device, up=up,
          ignore_geometry=args.ignore_geometry, public_url=args.public_url)
    return 0
