"""`s3k train`: command-line front end of :func:`s3k.train.train`; the options are the fields of
:class:`s3k.config.TrainConfig` (``s3k.cli.config_options``), the two-pass ones included."""

from __future__ import annotations

import argparse
import json
import sys

from s3k.base.errors import UserError
from s3k.base.messages import note
from s3k.base.outputs import check_output_folder
from s3k.cli import examples
from s3k.cli.config_options import add_config_arguments, config_from_args
from s3k.config import TrainConfig, leaf_fields, resumable_fields
from s3k.config_files import read_config_file
from s3k.run_folder import RunFolder
from s3k.train import train
from s3k.train.fine_tune import fine_tune_config
from s3k.train.presets import PRESETS, preset


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Train a keypoint detector (S3K: labelled + unlabelled frames; --no-unsup: labels-only baseline), "
        "on the whole image or, with --two-pass, coarse-to-fine (docs/accuracy.md). Run under 'torchrun "
        "--nproc-per-node N' for data-parallel training."
    )
    parser.epilog = examples("s3k train data/box --out runs/box",
                             "s3k train data/box --out runs/box-more --init-from runs/box --steps 500",
                             "s3k train data/box --out runs/box-2p --two-pass --rotation-deg 15 "
                             "--coarse-rotation 180 --layout-tol 0.2",
                             "s3k train data/box --out runs/box --preset box-fast --print-config")
    parser.add_argument("dataset", help="dataset folder (see docs/dataset-format.md)")
    parser.add_argument("--out", required=True, metavar="RUN", help="run folder to create (or to --resume)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last checkpoint (its configuration is used; "
                             "options given here may change only steps, threads, progress, device, "
                             "preloading and the validation, logging and checkpoint cadence; a --preset "
                             "must be the run's)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the run in --out (deletes only the files a run holds)")
    parser.add_argument("--init-from", default=None, metavar="RUN",
                        help="fine-tune, e.g. after adding labelled frames: start from RUN's network and "
                             "configuration (a two-pass RUN pass by pass, its crops' extent kept), each "
                             "pass at the learning rate RUN ended at (--lr x --lr-final), the "
                             "self-supervised term on from the first step; options given here or in --config "
                             "win over it, and a --preset replaces its configuration (default: a new "
                             "network)")
    parser.add_argument("--preset", choices=list(PRESETS), default=None,
                        help="a named configuration (options given here or in --config win over it): "
                             + "; ".join(f"{name}: {p.description}".replace("%", "%%")  # argparse formats it
                                         for name, p in PRESETS.items())
                             + " (default: none)")
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved configuration as JSON (the flat fields) and train nothing")
    add_config_arguments(parser, TrainConfig)


def resolve(args: argparse.Namespace) -> TrainConfig:
    """The configuration of this call: the preset (or, with ``--resume``, the run's own; or, with
    ``--init-from RUN`` and no preset, RUN's continued where it ended: :mod:`s3k.train.fine_tune`), the
    ``--config`` file over it, the options given over that. A preset given with ``--resume`` must be the
    run's: one that sets a field the resume may not change to another value than the run's is refused (as
    that field's option would be), naming the field."""
    base = preset(args.preset) if args.preset else None
    saved = RunFolder(args.out).config() if args.resume else None
    if saved is not None and base is not None:
        mine = config_from_args(args, TrainConfig, base=base).to_dict()
        theirs = config_from_args(args, TrainConfig, base=saved).to_dict()
        free = resumable_fields()
        for name, value in mine.items():
            if name not in free and value != theirs[name]:
                raise UserError(f"--resume: --preset {args.preset} sets {name} to {_shown(value)} but the "
                                f"run in {args.out} was trained with {_shown(theirs[name])}",
                                hint="drop --preset to continue the run with its own configuration, or "
                                     "choose another --out")
    if saved is None and args.init_from is not None:
        if base is None:
            base, line = fine_tune_config(args.init_from, given_fields(args))
            note(line)
        else:
            note(f"fine-tuning {args.init_from}: its network; the configuration is --preset {args.preset}'s, "
                 "not the run's")
    return config_from_args(args, TrainConfig, base=saved or base)


def _shown(value: object) -> str:
    return ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)


def given_fields(args: argparse.Namespace) -> set[str]:
    """The configuration's fields this call sets: on the command line or in ``--config FILE``."""
    given = {f.name for _, f, _ in leaf_fields(TrainConfig) if hasattr(args, f.name)}
    if args.config:
        given |= set(read_config_file(args.config))
    return given


def run(args: argparse.Namespace) -> int:
    cfg = resolve(args)
    if args.print_config:
        cfg.validate()
        print(json.dumps(cfg.to_dict(), indent=2))
        return 0
    check_output_folder(args.out, inputs={"DATASET": args.dataset, "--config": args.config})
    result = train(args.dataset, args.out, cfg, resume=args.resume, overwrite=args.overwrite,
                   command=getattr(args, "command_line", None), init_from=args.init_from)
    if result.status != "done":
        run = RunFolder(args.out)
        print(f"s3k train: error: training stopped at step {result.step} with non-finite values "
              f"({result.status}); {run.model} was not written; lower --lr, or see {run.log}",
              file=sys.stderr)
        return 1
    return 0
