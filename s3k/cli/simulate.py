"""``s3k simulate SCENE --out DIR``: render one of the paper's simulated datasets (see docs/scenes.md)."""

from __future__ import annotations

import argparse
import sys

from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.options import number
from s3k.sim.generate import MAX_SIZE
from s3k.sim.rigs import RIGS
from s3k.sim.scene import NUM_TRAIN_INSTANCES
from s3k.sim.scenes import SCENES


def number_pair(text: str) -> tuple[float, float]:
    """An ``argparse`` ``type=``: ``"LO,HI"`` -> ``(LO, HI)`` (the range itself is checked by
    :class:`s3k.sim.generate.SimulateConfig`)."""
    parts = text.split(",")
    try:
        lo, hi = (float(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers LO,HI, e.g. 10,85; got {text!r}") from None
    return lo, hi


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.epilog = examples("s3k simulate box --out data/box",
                             "s3k simulate distractors --out data/distractors --size 128 --labelled 30 "
                             "--preview distractors.png",
                             "s3k simulate box --out data/box-low --size 384 --labelled 0 --unlabelled 0 "
                             "--test 50 --seed 1000 --rig low",
                             "s3k simulate box --out data/box-wide-rig --size 384 --elevation 10,85")
    parser.add_argument("scene", choices=list(SCENES), help="which scene to render")
    parser.add_argument("--out", required=True, help="dataset folder to create")
    parser.add_argument("--size", type=number(int, ge=16, le=MAX_SIZE), default=96,
                        help="image width and height in pixels (default 96)")
    parser.add_argument("--labelled", type=number(int, ge=0), default=None,
                        help="labelled frames (default 10; plush: 7, one per training arrangement)")
    parser.add_argument("--unlabelled", type=number(int, ge=0), default=2000,
                        help="unlabelled frames (default 2000)")
    parser.add_argument("--test", type=number(int, ge=0), default=200, help="test frames (default 200)")
    parser.add_argument("--seed", type=number(int, ge=0), default=0,
                        help="sampling seed: object poses, cameras and lighting (default 0)")
    parser.add_argument("--object-seed", type=number(int, ge=0), default=0,
                        help="the scene's look: box texture, category shapes, distractor sets (default 0: "
                             "the same object whatever --seed)")
    parser.add_argument("--mode", choices=["start", "full"], default=None,
                        help="distractors: labelled frames from the first distractor segment only (start) or "
                             "spread over the whole timeline (full, the default)")
    parser.add_argument("--segments", type=number(int, ge=1), default=6,
                        help="distractors: training segments (distractor sets) on the timeline (default 6)")
    parser.add_argument("--test-segments", type=number(int, ge=1), default=2,
                        help="distractors: test segments, with distractor sets unseen in training "
                             "(default 2)")
    parser.add_argument("--train-instances", type=number(int, ge=1, le=NUM_TRAIN_INSTANCES), default=None,
                        help=f"category: train on the first N of the {NUM_TRAIN_INSTANCES} training "
                             f"instances (default {NUM_TRAIN_INSTANCES}); test frames use the 4 held out")
    parser.add_argument("--unlabelled-arrangements", type=number(int, ge=0), default=0,
                        help="plush: spread the unlabelled frames over this many further arrangements too "
                             "(new toy placements and camera rigs, in no test set; default 0)")
    parser.add_argument("--rig", choices=list(RIGS), default="train",
                        help="the cameras: the scene's own rig (train, the default) or one outside its "
                             "ranges for a test set: low or high elevations, far, or a wide lens "
                             "(docs/scenes.md)")
    parser.add_argument("--elevation", type=number_pair, default=None, metavar="LO,HI",
                        help="draw the cameras' elevations above the table from LO to HI degrees instead of "
                             "the scene's range (e.g. 10,85; --rig is then relative to it)")
    parser.add_argument("--distance", type=number_pair, default=None, metavar="LO,HI",
                        help="draw the cameras' distances from the aim point from LO to HI metres instead of "
                             "the scene's range")
    parser.add_argument("--fixed-rig", action="store_true",
                        help="draw the cameras once for the whole dataset, as a lab's rig stays put through "
                             "a recording (default: new cameras every frame)")
    parser.add_argument("--workers", type=number(int, ge=1), default=None,
                        help="rendering processes, one MuJoCo renderer each (default: CPUs available)")
    parser.add_argument("--overwrite", action="store_true", help="replace DIR if it exists and is not empty")
    parser.add_argument("--preview", default=None, metavar="PNG",
                        help="also write a contact sheet of 3 frames (first, middle, last; 4 views each) "
                             "to this PNG file (default: none)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from s3k.sim.generate import SimulateConfig, simulate

    if args.mode is not None and args.scene != "distractors":
        print(f"s3k simulate: --mode applies to the distractors scene only; ignored for {args.scene}",
              file=sys.stderr)
    if args.train_instances is not None and args.scene != "category":
        print(f"s3k simulate: --train-instances applies to the category scene only; ignored for {args.scene}",
              file=sys.stderr)
    if args.unlabelled_arrangements and args.scene != "plush":
        print(f"s3k simulate: --unlabelled-arrangements applies to the plush scene only; ignored for "
              f"{args.scene}", file=sys.stderr)
        args.unlabelled_arrangements = 0
    cfg = SimulateConfig(
        scene=args.scene, size=args.size,
        labelled=args.labelled if args.labelled is not None else (7 if args.scene == "plush" else 10),
        unlabelled=args.unlabelled,
        test=args.test, seed=args.seed, object_seed=args.object_seed, mode=args.mode or "full",
        segments=args.segments, test_segments=args.test_segments,
        train_instances=NUM_TRAIN_INSTANCES if args.train_instances is None else args.train_instances,
        unlabelled_arrangements=args.unlabelled_arrangements, rig=args.rig,
        elevation=args.elevation, distance=args.distance, fixed_rig=args.fixed_rig,
    )
    if args.preview:
        check_output(args.preview, args.overwrite, option="--preview")
    summary = simulate(cfg, args.out, workers=args.workers, progress=not args.no_progress,
                       overwrite=args.overwrite, preview=args.preview)
    print(f"wrote {summary['path']}: {summary['frames']} frames ({cfg.labelled} labelled, {cfg.unlabelled} "
          f"unlabelled, {cfg.test} test), 4 cameras, {cfg.size}x{cfg.size} px, in {summary['seconds']:.1f} s "
          f"({summary['images_per_s']:.0f} images/s)")
    return 0
