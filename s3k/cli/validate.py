"""`s3k validate`: check a dataset folder, report every problem (:func:`s3k.data.validate.validate_dataset`).

The exit status is 0 for a usable dataset (warnings allowed unless ``--strict``) and 1 otherwise.
"""

from __future__ import annotations

import argparse

from s3k.cli import examples
from s3k.cli.options import number
from s3k.data.validate import validate_dataset


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.epilog = examples("s3k validate data/box", "s3k validate data/session --no-images --strict")
    parser.add_argument("dataset", help="dataset folder (holds s3k.json)")
    parser.add_argument(
        "--no-images", action="store_true", help="only check that image files exist, do not decode them"
    )
    parser.add_argument("--workers", type=number(int, ge=1), default=None,
                        help="image decoding threads (default: CPUs)")
    parser.add_argument("--max-per-field", type=number(int, ge=0), default=10,
                        help="print at most this many problems per file and field (default: %(default)s)")
    parser.add_argument("--strict", action="store_true", help="exit non-zero on warnings too")


def run(args: argparse.Namespace) -> int:
    ok, lines = validate_dataset(
        args.dataset, check_images=not args.no_images, workers=args.workers,
        max_per_field=args.max_per_field, strict=args.strict,
    )
    print("\n".join(lines))
    return 0 if ok else 1
