"""The `s3k` command: one subcommand per task, each implemented in its own module.

A subcommand's module defines ``configure_parser(parser)`` and ``run(args) -> int``. Modules are imported only
when their command runs, so ``s3k --help`` stays fast and a missing optional dependency affects one command.
"""

from __future__ import annotations

import argparse
import importlib
import shlex
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("s3k.sim.cli", "render a simulated multi-view dataset (box, distractors, category)"),
    "validate": ("s3k.data.validate", "check a dataset folder and report every problem found"),
    "train": ("s3k.train", "train a keypoint detector (S3K or labels-only)"),
    "evaluate": ("s3k.evaluate", "compute rms_px, rms_px_reproj, median_mm, rms_mm and write a report"),
    "predict": ("s3k.predict", "write per-frame 3D keypoints of a dataset as CSV"),
    "demo": ("s3k.demo", "simulate the box scene, train S3K and the baseline, compare them"),
    "experiment": ("s3k.experiments", "run one of the paper's experiments as a resumable sweep"),
    "import": (
        "s3k.data.importers",
        "convert a recording (anipose, DeepLabCut, Lightning Pose, SLEAP) to a dataset",
    ),
    "check-calibration": ("s3k.calibration", "reprojection residual per camera from the labels"),
    "track": ("s3k.track", "3D keypoints from synchronized videos, anipose CSV out"),
    "export": ("s3k.export", "export a trained detector to ONNX or TorchScript"),
}


def _top_parser() -> argparse.ArgumentParser:
    lines = "\n".join(f"  {name:<18} {text}" for name, (_, text) in COMMANDS.items())
    parser = argparse.ArgumentParser(
        prog="s3k",
        description="Semantic 3D keypoints from a calibrated multi-camera rig.",
        epilog=f"commands:\n{lines}\n\nRun 's3k COMMAND --help' for a command's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("command", nargs="?", choices=list(COMMANDS), metavar="COMMAND")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    if not argv or argv[0].startswith("-"):
        args = top.parse_args(argv)
        if args.version:
            from s3k import __version__

            print(__version__)
        else:
            top.print_help()
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        top.error(f"unknown command {name!r}; choose from {', '.join(COMMANDS)}")
    module_name, text = COMMANDS[name]
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(prog=f"s3k {name}", description=text)
    module.configure_parser(parser)
    args = parser.parse_args(rest)
    args.command_line = shlex.join(["s3k", name, *rest])  # what was run, for commands that record it
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
