"""The fixed choices of settings, as ``Literal`` types: a checker catches a misspelt one, and the command line
offers exactly these (``s3k.cli.config_options`` turns a ``Literal`` field into ``choices``).

Example:
    >>> typing.get_args(Norm)
    ('batch', 'group', 'none')
"""

from __future__ import annotations

import typing
from typing import Literal

__all__ = ["ENCODERS", "FIT_MODES", "LAYOUT_FITS", "NORMS", "Arithmetic", "Device", "Encoder", "Fit",
           "LayoutFit", "Norm", "Precision"]

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
Device = Literal["auto", "cpu", "cuda"] | str
"""Where the network runs: ``"auto"`` (a GPU when there is one), ``"cpu"``, ``"cuda"``, or a device name torch
takes, such as ``"cuda:1"``."""

Fit = Literal["pad", "crop", "stretch"]
"""How a frame maps onto a detector's input when the aspect ratios differ (``--fit``;
:func:`s3k.detector.geometry_record.fit_box`)."""
LayoutFit = Literal["all", "kept", "off"]
"""Which keypoints a rigid read-out's fitted layout places (:class:`s3k.readout.ReadoutConfig`)."""

NORMS: tuple[str, ...] = typing.get_args(Norm)
FIT_MODES: tuple[str, ...] = typing.get_args(Fit)
LAYOUT_FITS: tuple[str, ...] = typing.get_args(LayoutFit)
ENCODERS: tuple[str, ...] = typing.get_args(Encoder)
