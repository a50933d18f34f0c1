"""Parsers of option values shared by several commands: numbers in a range, non-empty names,
``CAMERA=FILE`` pairs, crop boxes, image sizes, the rig of ``s3k track`` and ``s3k stream``.

:func:`number` and :func:`name` are ``type=`` functions of ``argparse``: a value out of range is refused when
the command line is parsed, before any work, as ``s3k CMD: error: argument --opt: must be > 0, got '0'``.
Every numeric option of every command is declared with one (``tests/cli/test_options.py`` checks it). The
others raise :class:`s3k.base.errors.UserError` naming the option and the value.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from s3k.base.choices import FIT_MODES, Device, parse_device
from s3k.base.errors import UserError
from s3k.base.ranges import Range
from s3k.data.rig import check_camera_name
from s3k.inference.session import RigOptions


def number(kind: type = float, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
           lt: float | None = None) -> Callable[[str], Any]:
    """An ``argparse`` ``type=``: text -> ``kind`` (int or float), finite and within the bounds.

    Example:
        >>> number(int, ge=1)("3")
        3
    """
    bounds = Range(ge=ge, gt=gt, le=le, lt=lt)

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            what = "an integer" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        problem = bounds.problem(value)
        if problem is not None:
            raise argparse.ArgumentTypeError(f"{problem}, got {text!r}")
        return value

    parse.__name__ = kind.__name__
    parse.range = bounds  # type: ignore[attr-defined]
    return parse


def device(text: str) -> Device:
    """An ``argparse`` ``type=`` for ``--device``: :func:`s3k.base.choices.parse_device`, refused as the
    command line is parsed."""
    try:
        return parse_device(text, "value")
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("value: ")) from None


def name(text: str) -> str:
    """An ``argparse`` ``type=`` for a name (a unit, a camera): not empty, no surrounding blanks."""
    if not text.strip() or text != text.strip():
        raise argparse.ArgumentTypeError(f"expected a name without surrounding blanks, got {text!r}")
    return text


def camera_pairs(values: list[str] | None, option: str) -> dict[str, str]:
    """``["cam=FILE", ...]`` -> ``{cam: FILE}`` in the order given, each camera's name checked
    (:func:`s3k.data.rig.check_camera_name`)."""
    out: dict[str, str] = {}
    for value in values or []:
        cam, sep, rest = value.partition("=")
        if not sep or not cam or not rest:
            raise UserError(f"{option} {value!r}: expected CAMERA=FILE")
        if cam in out:
            raise UserError(f"{option}: camera {cam!r} given twice")
        out[check_camera_name(cam, f"{option} {value!r}")] = rest
    return out


def parse_crops(values: list[str] | None, cameras: list[str], option: str = "--crop",
                every: bool = True) -> dict[str, tuple[float, ...]]:
    """``--crop`` values ``["x0,y0,x1,y1"]`` (every camera, unless ``every=False``) or
    ``["cam=x0,y0,x1,y1", ...]`` -> ``{cam: box}``; ``option`` names the option in errors."""
    crops: dict[str, tuple[float, ...]] = {}
    for value in values or []:
        cam, sep, box_text = value.rpartition("=")
        targets = [cam] if sep else list(cameras)
        if not sep and not every:
            raise UserError(f"{option} {value!r}: expected CAMERA=x0,y0,x1,y1")
        if sep and cam not in cameras:
            raise UserError(f"{option} {value!r}: unknown camera {cam!r} (cameras: {', '.join(cameras)})")
        try:
            box = tuple(float(x) for x in box_text.split(","))
        except ValueError:
            box = ()
        if (len(box) != 4 or not all(map(math.isfinite, box)) or not box[2] > box[0]
                or not box[3] > box[1]):
            raise UserError(f"{option} {value!r}: expected [CAMERA=]x0,y0,x1,y1, finite numbers with x1 > x0 "
                            "and y1 > y0")
        for t in targets:
            crops[t] = box
    return crops


def parse_size(text: str | None) -> int | tuple[int, int] | None:
    """``--size`` ``"PX"`` (the longer side) -> ``PX``; ``"W,H"`` -> ``(W, H)``; None -> None."""
    if text is None:
        return None
    try:
        nums = [int(p) for p in text.split(",")]
    except ValueError:
        nums = []
    if len(nums) == 2 and min(nums) > 0:
        return nums[0], nums[1]
    if len(nums) == 1 and nums[0] > 0:
        return nums[0]
    raise UserError(f"--size {text!r}: expected PX (longer side) or W,H")


def add_rig_options(parser: argparse.ArgumentParser, calibration_required: bool = True) -> None:
    """The options of a command that reads the synchronized frames of a calibrated rig through a run's
    detector (``s3k track``, ``s3k stream``): the calibration and its unit, the part of the calibrated image
    each camera shows, each camera's box onto the detector's input and the device
    (:class:`s3k.inference.session.RigOptions`, :func:`rig_options`)."""
    parser.add_argument("--calibration", required=calibration_required,
                        help="anipose calibration.toml, Qualisys .qca.txt, OpenCV/JARVIS .yaml/.xml or "
                        "DeepFly3D .pkl (as for 's3k import')")
    parser.add_argument("--video-region", nargs="+", default=None, metavar="CAM=X0,Y0,X1,Y1",
                        help="the region of the calibrated image a camera's frames show (as for "
                        "'s3k import'; default: the whole calibrated image)")
    parser.add_argument("--units", type=name, default=None,
                        help="world unit of the calibration when it does not say (default: the "
                             "calibration's)")
    parser.add_argument("--crop", nargs="+", default=None, metavar="[CAM=]X0,Y0,X1,Y1",
                        help="crop box in pixel edge coordinates, as given to 's3k import --crop' (default: "
                        "the boxes the run was trained on, from its dataset's import)")
    parser.add_argument("--fit", choices=FIT_MODES, default=None,
                        help="when a frame's aspect ratio differs from the detector's input: pad "
                        "(default), crop or stretch; given, it replaces the crop boxes the run was trained "
                        "on")
    add_device_option(parser)
    add_other_rig_option(parser)


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """``--device`` of the commands that run a detector (default auto)."""
    parser.add_argument("--device", type=device, default="auto",
                        help="'auto', 'cpu', 'cuda' or 'cuda:N' (default: auto)")


def add_detector_options(parser: argparse.ArgumentParser, batch_size: int = 16) -> None:
    """``--batch-size`` and ``--device`` of the commands that run a detector over a dataset's frames."""
    parser.add_argument("--batch-size", type=number(int, ge=1), default=batch_size,
                        help=f"frames per forward pass (default: {batch_size})")
    add_device_option(parser)


def add_other_rig_option(parser: argparse.ArgumentParser) -> None:
    """``--other-rig``: use a run on cameras (or a dataset's keypoints) it was not trained on
    (:func:`s3k.inference.rig_check.check_rig`)."""
    parser.add_argument("--other-rig", action="store_true",
                        help="use the run on cameras, keypoints or images other than those it was trained on "
                        "(refused by default: its results there are wrong)")


def add_frame_offsets_option(parser: argparse.ArgumentParser) -> None:
    """``--frame-offsets CAM=N``: cameras whose clocks are off (``s3k import`` and ``s3k track``)."""
    parser.add_argument("--frame-offsets", nargs="+", default=None, metavar="CAM=N",
                        help="cameras whose clocks are off (unsynchronized webcams): CAM=N says that the "
                        "camera's frame i shows the other cameras' frame i+N (s3k validate estimates N from "
                        "the labels' motion); several as CAM=N,CAM2=M or CAM=N CAM2=M (default: 0 for every "
                        "camera)")


def frame_offsets(values: list[str] | None, cameras: list[str]) -> dict[str, int] | None:
    """``--frame-offsets`` ``["cam=N,cam2=M", ...]`` -> ``{cam: N}``."""
    if not values:
        return None
    out: dict[str, int] = {}
    for item in (part for value in values for part in value.split(",") if part.strip()):
        cam, sep, text = item.strip().partition("=")
        try:
            n = int(text)
        except ValueError:
            sep = ""
        if not sep or cam not in cameras or cam in out:
            why = ("a camera given twice" if cam in out else f"unknown camera {cam!r}" if sep
                   else "expected CAMERA=N with N a whole number of frames")
            raise UserError(f"--frame-offsets {item.strip()!r}: {why} (cameras: {', '.join(cameras)})")
        out[cam] = n
    return out



def rig_options(args: argparse.Namespace, cameras: list[str]) -> RigOptions:
    """The :class:`s3k.inference.session.RigOptions` of :func:`add_rig_options`' options for ``cameras``."""
    return RigOptions(
        calibration=args.calibration, units=args.units,
        video_regions=parse_crops(args.video_region, cameras, "--video-region", every=False)
        if args.video_region else None,
        crops=parse_crops(args.crop, cameras) if args.crop else None, fit=args.fit, device=args.device,
        other_rig=args.other_rig,
        frame_offsets=frame_offsets(getattr(args, "frame_offsets", None), cameras))
