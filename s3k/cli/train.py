"""`s3k train`: command-line front end of :func:`s3k.train.train`; the options are the fields of
:class:`s3k.config.TrainConfig` (``s3k.cli.config_options``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from s3k.cli import examples
from s3k.cli.config_options import add_config_arguments, config_from_args
from s3k.cli.options import number
from s3k.config import TrainConfig, config_from_dict
from s3k.detector import CONFIG_FILE, is_two_pass, read_run_config
from s3k.errors import UserError
from s3k.outputs import check_output_folder
from s3k.presets import PRESETS, preset
from s3k.train import train
from s3k.train.two_pass import REFERENCE_CROP, train_two_pass
from s3k.train.two_pass_start import DEFAULTS, OPTIONS_FILE, read_options


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Train a keypoint detector (S3K: labelled + unlabelled frames; --no-unsup: labels-only baseline). "
        "Run under 'torchrun --nproc-per-node N' for data-parallel training."
    )
    parser.epilog = examples("s3k train data/box --out runs/box",
                             "s3k train data/box --out runs/box-more --init-from runs/box --steps 500 "
                             "--lr 3e-4",
                             "s3k train data/box --out runs/box-2p --two-pass --rotation-deg 15 "
                             "--coarse-rotation 180 --layout-tol 0.2")
    parser.add_argument("dataset", help="dataset folder (see docs/dataset-format.md)")
    parser.add_argument("--out", required=True, metavar="RUN", help="run folder to create (or to --resume)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last checkpoint (its config.json is used; "
                             "options given here may change only steps, threads, progress, device, "
                             "preloading and the validation, logging and checkpoint cadence)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the run in --out (deletes only the files a run holds)")
    parser.add_argument("--init-from", default=None, metavar="RUN",
                        help="fine-tune: start from RUN's network (same keypoints and architecture; a "
                             "two-pass RUN with --two-pass, its crops' extent kept) with this run's own "
                             "--steps, --lr and schedule, e.g. after adding labelled frames (default: a new "
                             "network)")

    parser.add_argument("--preset", choices=list(PRESETS), default=None,
                        help="a named configuration (options given here or in --config win over it): "
                             + "; ".join(f"{name}: {p.description}".replace("%", "%%")  # argparse formats it
                                         for name, p in PRESETS.items())
                             + " (default: none)")
    two = parser.add_argument_group(
        "two passes (coarse-to-fine; docs/accuracy.md)",
        "--two-pass trains a coarse detector on the whole image, crops every view around its 3D estimate "
        "(a fixed extent in world units, so the object has one size in every crop) and trains a refining "
        "detector on the crops; the options below the configuration apply to both passes, --image-size to "
        "neither")
    two.add_argument("--two-pass", action="store_true", help="train the coarse-to-fine detector")
    two.add_argument("--coarse-size", type=number(int, ge=16), default=None, metavar="PX",
                     help="the coarse pass's image size, longer side (default 96)")
    two.add_argument("--coarse-steps", type=number(int, ge=1), default=None, metavar="N",
                     help="the coarse pass's steps (default: --steps)")
    two.add_argument("--coarse-rotation", type=number(ge=0), default=None, metavar="DEG",
                     help="the coarse pass's augmentation rotation range in degrees (default: "
                          "--rotation-deg), e.g. 180 with --rotation-deg 15: a coarse pass that finds the "
                          "object in any pose and a precise refining pass")
    two.add_argument("--coarse-stride", type=number(int, ge=1, le=4), default=None, metavar="{1,2,4}",
                     help="the coarse pass's heatmap stride (default: --stride), e.g. 2 with --stride 4: a "
                          "coarse pass that places the crops well under a cheaper refining pass")
    two.add_argument("--coarse-lr", type=number(gt=0, le=1), default=None, metavar="FLOAT",
                     help="the coarse pass's learning rate (default: --lr), e.g. to train a refining pass at "
                          "another --lr on a finished coarse pass")
    two.add_argument("--crop-size", type=number(int, ge=16), default=None, metavar="PX",
                     help=f"crop size in pixels, the refining pass's input (default {REFERENCE_CROP}); the "
                          f"refining pass scales --outlier-px, --shift-px and --pseudo-window by "
                          f"PX/{REFERENCE_CROP} so they keep their size in the scene")
    two.add_argument("--crop-margin", type=number(ge=0), default=None, metavar="F",
                     help="crop side = 2 x (largest distance of a labelled keypoint from the middle of its "
                          "frame's keypoints) x (1 + F) (default 0.3)")
    two.add_argument("--crop-extent", type=number(gt=0), default=None, metavar="W",
                     help="crop side in world units at the estimate's depth (default: from the labels)")
    two.add_argument("--keep-crops", action="store_true",
                     help="also write the refining pass's crops as a dataset folder, RUN/crops (they are cut "
                          "and used in memory otherwise)")
    add_config_arguments(parser, TrainConfig)


def run(args: argparse.Namespace) -> int:
    check_output_folder(args.out, inputs={"DATASET": args.dataset, "--config": args.config})
    chosen = _preset(args)
    if args.two_pass:
        return _run_two_pass(args, chosen)
    base = chosen
    if args.resume and (Path(args.out) / CONFIG_FILE).is_file():
        saved = read_run_config(args.out)["config"]
        base = config_from_dict(TrainConfig, saved, where=f"{Path(args.out) / CONFIG_FILE}")
    cfg = config_from_args(args, TrainConfig, base=base)
    if args.init_from is not None and _is_two_pass(args.init_from):

        raise UserError(f"--init-from {args.init_from}: a two-pass run",
                        hint="add --two-pass to fine-tune it")
    result = train(args.dataset, args.out, cfg, resume=args.resume, overwrite=args.overwrite,
                   command=getattr(args, "command_line", None), init_from=args.init_from)
    if result.status != "done":
        print(f"s3k train: error: training stopped at step {result.step} with non-finite values "
              f"({result.status}); {Path(args.out) / 'model.pt'} was not written; lower --lr, or see "
              f"{Path(args.out) / 'train.log'}", file=sys.stderr)
        return 1
    return 0


def _is_two_pass(run: str) -> bool:

    return is_two_pass(run)


def _preset(args: argparse.Namespace) -> TrainConfig | None:
    """The configuration of ``--preset`` (None without one); a two-pass preset turns on ``--two-pass`` and
    gives the two-pass options that the command line leaves out."""
    if args.preset is None:
        return None

    chosen = preset(args.preset)
    if chosen.two_pass is not None:
        args.two_pass = True
        names = {"margin": "crop_margin", "extent": "crop_extent"}
        for key, value in chosen.two_pass.items():
            if getattr(args, names.get(key, key)) is None:
                setattr(args, names.get(key, key), value)
    return config_from_dict(TrainConfig, chosen.config, where=f"--preset {args.preset}")


def _run_two_pass(args: argparse.Namespace, chosen: TrainConfig | None = None) -> int:
    saved = read_options(args.out) if args.resume else None
    where = f"{Path(args.out) / OPTIONS_FILE}"
    base = chosen if saved is None else config_from_dict(TrainConfig, saved[0], where=where)
    cfg = config_from_args(args, TrainConfig, base=base)  # --resume: the run's own, changed by options given
    if cfg.image_size:
        raise UserError("--image-size does not apply to --two-pass",
                        hint="set the coarse pass's size with --coarse-size and the crops' with --crop-size")
    given = {"coarse_size": args.coarse_size, "coarse_steps": args.coarse_steps,
             "coarse_rotation": args.coarse_rotation, "coarse_stride": args.coarse_stride,
             "coarse_lr": args.coarse_lr,
             "crop_size": args.crop_size, "margin": args.crop_margin, "extent": args.crop_extent}
    options = {k: v if v is not None else (saved[1] if saved else DEFAULTS)[k] for k, v in given.items()}
    train_two_pass(args.dataset, args.out, cfg, **options, resume=args.resume, overwrite=args.overwrite,
                   command=getattr(args, "command_line", None), keep_crops=args.keep_crops,
                   init_from=args.init_from)
    return 0
