"""Parsers of option values shared by several commands: numbers in a range, non-empty names,
``CAMERA=FILE`` pairs, crop boxes, image sizes.

:func:`number` and :func:`name` are ``type=`` functions of ``argparse``: a value out of range is refused when
the command line is parsed, before any work, as ``s3k CMD: error: argument --opt: must be > 0, got '0'``.
Every numeric option of every command is declared with one (``tests/test_options.py`` checks it). The others
raise :class:`s3k.errors.UserError` naming the option and the value.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from s3k.data.rig import check_camera_name
from s3k.detector.geometry_record import run_meta
from s3k.errors import UserError
from s3k.inference.kalman import MODELS, RANGES, FilterSettings
from s3k.inference.track import FIT_MODES
from s3k.inference.track_filter import check_rigid, layout_shape_of
from s3k.ranges import Range
from s3k.readout import DEFAULT_MIN_WEIGHT


def number(kind: type = float, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
           lt: float | None = None, within: Range | None = None) -> Callable[[str], Any]:
    """An ``argparse`` ``type=``: text -> ``kind`` (int or float), finite and within the bounds (``within``: a
    :class:`s3k.ranges.Range` declared beside the setting, in place of the bounds).

    Example:
        >>> number(int, ge=1)("3")
        3
    """
    bounds = within if within is not None else Range(ge=ge, gt=gt, le=le, lt=lt)

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


def add_rig_options(parser: argparse.ArgumentParser) -> None:
    """The options of a command that reads the synchronized frames of a calibrated rig through a run's
    detector (``s3k track``, ``s3k stream``): the calibration and its unit, the part of the calibrated image
    each camera shows, each camera's box onto the detector's input, the views' confidence and the device."""
    parser.add_argument("--calibration", required=True,
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
    parser.add_argument("--min-weight", type=number(ge=0, lt=1), default=DEFAULT_MIN_WEIGHT,
                        help="confidence weight a view needs to be used (default 0: every view, weighted by "
                        "its confidence, as in training and 's3k evaluate'; 0.5 drops views whose heatmap "
                        "spread exceeds 2 sigma)")
    parser.add_argument("--device", default="auto", help="'auto', 'cpu', 'cuda' (default: auto)")
    add_other_rig_option(parser)


def add_other_rig_option(parser: argparse.ArgumentParser) -> None:
    """``--other-rig``: use a run on cameras (or a dataset's keypoints) it was not trained on
    (:func:`s3k.inference.rig_check.check_rig`)."""
    parser.add_argument("--other-rig", action="store_true",
                        help="use the run on cameras, keypoints or images other than those it was trained on "
                        "(refused by default: its results there are wrong)")


def add_filter_options(parser: argparse.ArgumentParser, default: str) -> None:
    """The options of the filter over time (``s3k track`` offline, ``s3k stream`` causal;
    :class:`s3k.inference.kalman.FilterSettings`), ``--filter`` defaulting to ``default``."""

    g = parser.add_argument_group(
        "filtering over time (docs/tracks.md)",
        "a Kalman filter in 3D per keypoint whose measurement noise comes from each detection's confidence "
        "and reprojection residual; jumps beyond the innovation gate are rejected and bridged, as are short "
        "gaps; a rigid object's layout and a skeleton's limb lengths hold the points as soft constraints")
    g.add_argument("--filter", choices=("kalman", "none"), default=default,
                   help=f"filter the 3D points over time (default {default})")
    g.add_argument("--filter-model", choices=list(MODELS), default="velocity",
                   help="motion model of each keypoint: constant velocity or constant acceleration (default "
                        "velocity)")
    g.add_argument("--filter-process-noise", type=_ranged("process_noise"), default=None, metavar="Q",
                   help="standard deviation of the white noise driving the motion, world units per frame "
                        "squared (cubed for acceleration) (default: fitted per keypoint by likelihood)")
    g.add_argument("--filter-noise-scale", type=_ranged("noise_scale"), default=None, metavar="S",
                   help="scale of the measurement noise (default: fitted per keypoint by likelihood)")
    g.add_argument("--filter-noise-px", type=_ranged("noise_px"), default=None, metavar="PX",
                   help="least reprojection residual a detection counts with, pixels (default: the "
                        "keypoint's median residual)")
    g.add_argument("--filter-gate", type=_ranged("gate"), default=4.0, metavar="SIGMAS",
                   help="reject a point further than this many standard deviations from the prediction "
                        "(default 4; 0: never; at most 100)")
    g.add_argument("--filter-max-gap", type=_ranged("max_gap", int), default=10, metavar="FRAMES",
                   help="bridge up to this many missing or rejected frames; after a longer gap the filter "
                        "starts again (default 10)")
    g.add_argument("--filter-rigid", choices=("auto", "on", "off"), default="auto",
                   help="hold the points to the rigid layout the run was trained with (--layout-tol); auto: "
                        "when it has one (default auto)")
    g.add_argument("--filter-layout-std", type=_ranged("layout_std"), default=None, metavar="W",
                   help="how far a point may stand off the rigid layout, world units (default: fitted)")
    g.add_argument("--filter-limbs", nargs="+", default=None, metavar="A,B",
                   help="limbs (pairs of keypoints) whose lengths are held near their median over the track, "
                        "or 'none' (default: the skeleton the run recorded from its dataset, if any)")
    g.add_argument("--filter-limb-std", type=_ranged("limb_std"), default=None, metavar="W",
                   help="how far a limb's length may stand off its median, world units (default: its robust "
                        "spread over the track)")


def _ranged(setting: str, kind: type = float) -> Callable[[str], Any]:
    """The ``type=`` of a filter option: the range :data:`s3k.inference.kalman.RANGES` declares."""
    return number(kind, within=RANGES[setting])


def filter_settings(args: argparse.Namespace):
    """The :class:`s3k.inference.kalman.FilterSettings` of :func:`add_filter_options`' options."""

    rigid = {"auto": None, "on": True, "off": False}[args.filter_rigid]
    return FilterSettings(method=args.filter, model=args.filter_model,
                          process_noise=args.filter_process_noise, noise_scale=args.filter_noise_scale,
                          noise_px=args.filter_noise_px, gate=args.filter_gate, max_gap=args.filter_max_gap,
                          rigid=rigid, layout_std=args.filter_layout_std,
                          limb_std=args.filter_limb_std).check()


def check_filter_rigid(args: argparse.Namespace, run: str) -> None:
    """Refuse ``--filter-rigid on`` with a run that records no rigid layout, before any frame is read
    (:func:`s3k.inference.track_filter.check_rigid`)."""
    meta = run_meta(run)
    if meta is None or args.filter_rigid != "on":
        return  # a folder that is no run is refused as the detector is loaded
    try:
        shape = layout_shape_of(meta.get("layout"))
    except (TypeError, ValueError):
        return  # a layout that cannot be read is refused as the detector is loaded
    check_rigid(filter_settings(args), shape, f"the run {run}")


def filter_limbs(args: argparse.Namespace) -> list[tuple[str, str]] | None:
    """The pairs of ``--filter-limbs`` (``[]`` for ``none``), or None: the skeleton the run recorded."""
    if args.filter_limbs is None:
        return None
    if args.filter_limbs == ["none"]:
        return []
    pairs = []
    for text in args.filter_limbs:
        a, sep, b = text.partition(",")
        if not sep or not a or not b or "," in b:
            raise UserError(f"--filter-limbs {text!r}: expected two keypoint names A,B")
        pairs.append((a, b))
    return pairs
