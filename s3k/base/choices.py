"""The fixed choices of settings, as ``Literal`` types: a checker catches a misspelt one, and the command line
offers exactly these (``s3k.cli.config_options`` turns a ``Literal`` field into ``choices``). A device names
a GPU by its index as well (``cuda:1``), so :data:`Device` is the literal names or a :data:`CudaDevice` that
only :func:`parse_device` makes from text: the command line, config files and the library's entry points
read a device through it, and a checker sees every other device name is one of these.

Example:
    >>> typing.get_args(Norm)
    ('batch', 'group', 'none')
    >>> parse_device("cuda:1")
    'cuda:1'
"""

from __future__ import annotations

import re
import typing
from typing import Literal, NewType

from s3k.base.errors import UserError

__all__ = ["DEVICE_NAMES", "ENCODERS", "FIT_MODES", "LAYOUT_FITS", "NORMS", "Arithmetic", "CudaDevice",
           "Device", "Encoder", "Fit", "FilterMethod", "LayoutFit", "MotionModel", "Norm", "Precision",
           "parse_device"]

Precision = Literal["auto", "float32", "bfloat16"]
"""A training's arithmetic (``--precision``): float32, bfloat16 autocast, or ``"auto"`` (bfloat16 where the
hardware computes it natively, else float32)."""
Arithmetic = Literal["float32", "bfloat16", "float16"]
"""A network's arithmetic as it runs (a training's :data:`Precision` resolved, or a detector's)."""
Norm = Literal["batch", "group", "none"]
"""The U-Net's normalization after each convolution."""
Encoder = Literal["unet", "efficientnet-lite0"]
"""The detector's encoder: the small U-Net's own, trained from scratch, or an ImageNet EfficientNet-Lite0
under a U-Net decoder (``s3k.networks``)."""
CudaDevice = NewType("CudaDevice", str)
"""One CUDA GPU by its index, ``"cuda:N"``: made by :func:`parse_device` alone."""
Device = Literal["auto", "cpu", "cuda"] | CudaDevice
"""Where the network runs: ``"auto"`` (a GPU when there is one), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``."""
DEVICE_NAMES = "auto, cpu, cuda or cuda:N"
_GPU = re.compile(r"cuda:[0-9]+")

Fit = Literal["pad", "crop", "stretch"]
"""How a frame maps onto a detector's input when the aspect ratios differ (``--fit``;
:func:`s3k.detector.geometry_record.fit_box`)."""
LayoutFit = Literal["all", "kept", "off"]
"""Which keypoints a rigid read-out's fitted layout places (:class:`s3k.readout.ReadoutConfig`)."""
FilterMethod = Literal["kalman", "none"]
"""Whether a track's 3D points are filtered over time (``--filter``)."""
MotionModel = Literal["velocity", "acceleration"]
"""The filter's motion model of each keypoint (``--filter-model``)."""

NORMS: tuple[str, ...] = typing.get_args(Norm)
FIT_MODES: tuple[str, ...] = typing.get_args(Fit)
LAYOUT_FITS: tuple[str, ...] = typing.get_args(LayoutFit)
ENCODERS: tuple[str, ...] = typing.get_args(Encoder)


def parse_device(text: object, where: str = "--device") -> Device:
    """``text`` as a :data:`Device`: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.

    Raises:
        UserError: one line naming ``where`` (the option, or the file and field) and the value.
    """
    if text in ("auto", "cpu", "cuda"):
        return typing.cast(Device, text)
    if isinstance(text, str) and _GPU.fullmatch(text):
        return CudaDevice(text)
    raise UserError(f"{where}: {text!r} is not a device", hint=f"pass {DEVICE_NAMES}")
