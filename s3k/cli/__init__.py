"""The `s3k` command: one subcommand per module of this package.

A command's module (``s3k/cli/<name>.py``) defines ``configure_parser(parser)`` and ``run(args) -> int``; it
parses and checks the options and calls library functions with typed arguments. Argument parsing lives only
here: library modules never see an ``argparse.Namespace``. Modules are imported only when their command runs,
so ``s3k --help`` stays fast and a missing optional dependency affects one command.

Options are spelled with dashes (``--rotation-deg``, booleans ``--flag/--no-flag``); a training field's own
name (``--rotation_deg``) is a hidden alias (:func:`s3k.cli.config_options.add_config_arguments`). Every
command's ``--help`` states the options' defaults and ends with examples (:func:`examples`).

Every command runs under one error handler (:func:`main`): a user error (:class:`s3k.base.errors.UserError`, a
missing or unreadable file, a corrupt archive) prints ``s3k COMMAND: error: ...`` in one line and exits with
status 1; ``--debug`` or ``S3K_DEBUG=1`` shows the traceback instead.

The library never prints: its modules log to ``logging.getLogger(__name__)``. While a command runs, the
``s3k`` logger's messages are shown as the command's own (:class:`_Messages`): notes and results on standard
output, warnings on standard error as ``warning: ...``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import shlex
import sys
from typing import Any

from s3k import __version__
from s3k.base.errors import UserError

# name -> (module in s3k.cli, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("simulate", "render a simulated multi-view dataset (box, distractors, category, plush)"),
    "validate": ("validate", "check a dataset folder and report every problem found"),
    "train": ("train", "train a keypoint detector (S3K or labels-only)"),
    "evaluate": ("evaluate", "compute rms_px, rms_px_reproj, median_mm, rms_mm and write a report"),
    "predict": ("predict", "write per-frame 3D keypoints of a dataset as CSV"),
    "demo": ("demo", "simulate the box scene, train S3K and the baseline, compare them"),
    "experiment": ("experiment", "run one of the paper's experiments as a resumable sweep"),
    "import": (
        "import_",
        "convert a recording (anipose, DeepLabCut, Lightning Pose, SLEAP, NWB) to a dataset",
    ),
    "calibrate": ("calibrate", "calibrate a whole rig from board videos or image folders, anipose TOML out"),
    "check-calibration": ("check_calibration", "reprojection residual per camera from the labels"),
    "track": ("track", "3D keypoints from synchronized videos, anipose CSV out"),
    "stream": ("stream", "live 3D keypoints from synchronized cameras or videos, one JSON line per frame"),
    "crops": ("crops", "each camera's crop box around the object, found by a run, for import --crop"),
    "add-frames": ("add_frames", "queue the frames a track was most in doubt about for labelling"),
    "view": ("view", "a dataset, a run's detections or tracks in 3D with the cameras, in Rerun"),
    "export": ("export", "export a trained detector to ONNX or TorchScript"),
    "export-labels": ("export_labels", "a dataset's 2D labels for DeepLabCut, Lightning Pose, SLEAP, NWB"),
    "export-tracks": ("export_tracks", "write 3D keypoints (track / predict CSV) as NWB"),
    "robot": ("robot", "keypoints in the loop: plush grasp trials, cable-insertion agents, their summary"),
    "label": ("label", "label keypoints in the browser; 'label propagate' copies labels over still frames"),
}


class HelpFormatter(argparse.HelpFormatter):
    """``--help`` text: a line of prose is wrapped to the terminal's width; a line that starts with a blank
    (an example command, a row of a table) is kept as written, and so are blank lines between paragraphs."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        lines = []
        for line in text.splitlines():
            if not line.strip():
                lines.append("")
            elif line[0].isspace():
                lines.append(indent + line)
            else:
                lines.append(super()._fill_text(line, width, indent))
        return "\n".join(lines)


def examples(*commands: str) -> str:
    """A parser's ``epilog``: the example command lines, one a line, under ``examples:``."""
    return "examples:\n" + "\n".join(f"  {c}" for c in commands)


def _top_parser() -> argparse.ArgumentParser:
    lines = "\n".join(f"  {name:<18} {text}" for name, (_, text) in COMMANDS.items())
    parser = argparse.ArgumentParser(
        prog="s3k",
        description="Semantic 3D keypoints from a calibrated multi-camera rig.",
        epilog=f"commands:\n{lines}\n\nRun 's3k COMMAND --help' for a command's options; "
               "'s3k --debug COMMAND ...' (or S3K_DEBUG=1) shows a traceback on error.\n\n"
               + examples("s3k demo --quick --out s3k-demo-quick", "s3k train data/box --out runs/box"),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    parser.add_argument("command", nargs="?", choices=list(COMMANDS), metavar="COMMAND")
    return parser


class _Parser(argparse.ArgumentParser):
    """A command's parser: a refused option is one line, ``s3k CMD: error: argument --opt: ...``, naming the
    value and where to read about the options (status 2, as ``argparse``'s own); help is laid out by
    :class:`HelpFormatter` (also in a subcommand's parser, which ``add_subparsers`` makes of this class)."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def _get_option_tuples(self, option_string: str):  # type: ignore[override]
        # An abbreviation that matches an option and its hidden alias (--rot: --rotation-deg and
        # --rotation_deg) means the option, not an ambiguity between two spellings of it.
        found = super()._get_option_tuples(option_string)
        shown = [t for t in found if getattr(t[0], "alias_of", None) is None]
        return shown or found

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}; see '{self.prog} --help'\n")


def command_parser(name: str, module: Any = None) -> _Parser:
    """The parser of the command ``name`` (its module imported unless given)."""
    module_name, text = COMMANDS[name]
    module = module or importlib.import_module(f"s3k.cli.{module_name}")
    parser = _Parser(prog=f"s3k {name}", description=text)
    module.configure_parser(parser)
    return parser


def describe_error(exc: BaseException) -> str | None:
    """The one-line message for an error a user can fix, or None for a bug (which keeps its traceback).

    User errors are :class:`s3k.base.errors.UserError` (and the data layer's ``DatasetError``, a subclass) and
    the operating system's refusals (missing file, permission, full disk), which are reported with the path
    they name.
    """
    if isinstance(exc, UserError):
        return str(exc)
    if isinstance(exc, OSError):
        what = exc.strerror or str(exc)
        name = exc.filename
        if name is not None:
            extra = f" -> {exc.filename2}" if getattr(exc, "filename2", None) else ""
            return f"{name}{extra}: {what}"
        return what
    return None


class _Messages(logging.Handler):
    """The library's log records as a command's output (:mod:`s3k.base.messages`): INFO and below on stdout as
    written, NOTE on stderr as written, WARNING and above on stderr prefixed ``warning: ``. The streams are
    looked up at each record, so a redirected ``sys.stdout`` (a test's capture) receives them."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
        except Exception:  # noqa: BLE001 - a malformed record is logging's own error to report
            self.handleError(record)
            return
        if record.levelno >= logging.WARNING:
            print(f"warning: {text}", file=sys.stderr)
        elif record.levelno > logging.INFO:
            print(text, file=sys.stderr)
        else:
            print(text, file=sys.stdout)


@contextlib.contextmanager
def showing_library_messages():
    """Show the ``s3k`` logger's INFO and WARNING records as the command's output while the block runs."""
    logger = logging.getLogger("s3k")
    handler, level = _Messages(logging.INFO), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = os.environ.get("S3K_DEBUG", "") not in ("", "0")
    while argv and argv[0] == "--debug":
        debug, argv = True, argv[1:]
    top = _top_parser()
    if not argv or argv[0].startswith("-"):
        args = top.parse_args(argv)
        if args.version:
            print(__version__)
        else:
            top.print_help()
        return 0
    name, rest = argv[0], argv[1:]
    if "--debug" in rest:
        debug, rest = True, [a for a in rest if a != "--debug"]
    if name not in COMMANDS:
        top.error(f"unknown command {name!r}; choose from {', '.join(COMMANDS)}")
    module = importlib.import_module(f"s3k.cli.{COMMANDS[name][0]}")
    args = command_parser(name, module).parse_args(rest)
    args.command_line = shlex.join(["s3k", name, *rest])  # what was run, for commands that record it
    try:
        with showing_library_messages():
            return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print(f"s3k {name}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place that turns user errors into one line
        message = None if debug else describe_error(exc)
        if message is None:
            raise
        print(f"s3k {name}: error: {message}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
