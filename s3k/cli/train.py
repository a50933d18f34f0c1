"""`s3k train`: command-line front end of :func:`s3k.train.train`; the options are the fields of
:class:`s3k.config.TrainConfig` (``s3k.cli.config_options``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from s3k.cli.config_options import add_config_arguments, config_from_args
from s3k.config import TrainConfig, config_from_dict
from s3k.run import CONFIG_FILE, read_run_config


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Train a keypoint detector (S3K: labelled + unlabelled frames; --no-unsup: labels-only baseline). "
        "Run under 'torchrun --nproc_per_node N' for data-parallel training."
    )
    parser.add_argument("dataset", help="dataset folder (see docs/dataset-format.md)")
    parser.add_argument("--out", required=True, metavar="RUN", help="run folder to create (or to --resume)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last checkpoint (its config.json is used; "
                             "options given here may change only steps, threads, progress, device, "
                             "preloading and the validation, logging and checkpoint cadence)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the run in --out (deletes only the files a run holds)")
    add_config_arguments(parser, TrainConfig)


def run(args: argparse.Namespace) -> int:
    from s3k.train import train

    base = None
    if args.resume and (Path(args.out) / CONFIG_FILE).is_file():
        saved = read_run_config(args.out)["config"]
        base = config_from_dict(TrainConfig, saved, where=f"{Path(args.out) / CONFIG_FILE}")
    cfg = config_from_args(args, TrainConfig, base=base)
    result = train(args.dataset, args.out, cfg, resume=args.resume, overwrite=args.overwrite,
                   command=getattr(args, "command_line", None))
    return 0 if result.status == "done" else 1
