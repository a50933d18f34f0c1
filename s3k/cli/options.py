"""Parsers of option values shared by several commands: ``CAMERA=FILE`` pairs, crop boxes, image sizes.

Each raises :class:`s3k.errors.UserError` naming the option and the value.
"""

from __future__ import annotations

from s3k.errors import UserError


def camera_pairs(values: list[str] | None, option: str) -> dict[str, str]:
    """``["cam=FILE", ...]`` -> ``{cam: FILE}`` in the order given."""
    out: dict[str, str] = {}
    for value in values or []:
        cam, sep, rest = value.partition("=")
        if not sep or not cam or not rest:
            raise UserError(f"{option} {value!r}: expected CAMERA=FILE")
        if cam in out:
            raise UserError(f"{option}: camera {cam!r} given twice")
        out[cam] = rest
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
        if len(box) != 4 or not box[2] > box[0] or not box[3] > box[1]:
            raise UserError(f"{option} {value!r}: expected [CAMERA=]x0,y0,x1,y1 with x1 > x0 and y1 > y0")
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
