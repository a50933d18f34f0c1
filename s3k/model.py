"""The keypoint network: a small U-Net mapping one camera image to K heatmap logits (docs/method.md#network).

One set of weights serves every camera: callers fold frames and cameras ``(B, C)`` into the batch ``N``
(:func:`detect` does it). The network is built for CPU speed: plain 3x3 convolutions, BatchNorm (folded into
the convolutions for inference by :meth:`UNet.fused`) and ReLU, 16-32 channels, additive skip connections, and
a stem that goes straight to the heatmap stride.

Layout for ``channels = (c0, c1, ..., cD)`` and heatmap stride ``s``::

    image (N, 3, H, W)
      stem: conv k x k, stride s             -> (N, c0, H/s, W/s)       level 0, the heatmap grid
      down: conv 3x3 stride 2 (+ extra convs) -> (N, c1, H/2s, W/2s)     level 1
      ...                                     -> (N, cD, H/2^D s, ...)   level D (bottom)
      bottom: res_blocks x [3 convs of cD channels + identity]
      up (per level, D-1 ... 0): 1x1 conv to c_l, nearest x2, + skip of level l, conv 3x3
      head: 1x1 conv c0 -> K (a GEMM)         -> (N, K, H/s, W/s) logits

The stem's kernel is ``2 s`` wide with padding ``s / 2`` (3x3 at ``s = 1``), so each heatmap cell's receptive
field is centred on the centre of the pixel block the cell covers (``heatmaps.cell_centres``).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any, cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from s3k import readout
from s3k.base.choices import ENCODERS, NORMS, Encoder, Norm
from s3k.readout.heatmaps import heatmap_size

__all__ = ["UNetConfig", "UNet", "detect", "conv_layers", "count_conv_flops"]



@dataclass
class UNetConfig:
    """Architecture of :class:`UNet`. Every field can be set from a config file or the command line."""

    in_channels: int = 3
    """Image channels (3 for RGB)."""
    channels: tuple[int, ...] = (16, 32, 32, 32)
    """Feature channels per level, level 0 at heatmap resolution; ``len(channels) - 1`` downsamplings by 2.
    The paper found 16-32 channels as accurate as more, and more only slower."""
    res_blocks: int = 2
    """Residual blocks at the bottom (lowest resolution), each of 3 convolutions with ``channels[-1]``
    channels and an identity shortcut (the paper's ResNet-style blocks of 32 channels)."""
    encoder_convs: int = 0
    """Extra 3x3 convolutions after each downsampling convolution of the encoder (levels 1 .. D)."""
    stride: int = 2
    """Heatmap stride: image pixels per heatmap cell along each axis, 1, 2 or 4. At 128 px, stride 2 gives
    64 x 64 heatmaps."""
    norm: Norm = "batch"
    """Normalization after each convolution: ``"batch"`` (BatchNorm, folded away at inference by
    :meth:`UNet.fused`), ``"group"`` (GroupNorm with groups of 8 channels; independent of batch composition)
    or ``"none"``."""
    encoder: Encoder = "unet"
    """The encoder: ``"unet"`` (the layout above) or ``"efficientnet-lite0"`` (:mod:`s3k.networks`: an
    EfficientNet-Lite0 cut at ``encoder_stride`` under a decoder of ``channels``)."""
    encoder_stride: int = 16
    """A pretrained encoder's deepest stride (8, 16 or 32: where it is cut); unused by ``"unet"``."""

    def __post_init__(self) -> None:
        self.channels = tuple(int(c) for c in self.channels)
        if len(self.channels) < 1 or any(c < 1 for c in self.channels):
            raise ValueError(f"UNetConfig.channels must be non-empty, all >= 1, got {self.channels}")
        if self.stride not in (1, 2, 4):
            raise ValueError(f"UNetConfig.stride must be 1, 2 or 4, got {self.stride!r}")
        if self.norm not in NORMS:
            raise ValueError(f"UNetConfig.norm must be one of {NORMS}, got {self.norm!r}")
        if self.norm == "group" and any(c % min(8, c) for c in self.channels):
            raise ValueError(f"UNetConfig.norm='group' needs channels divisible by 8, got {self.channels}")
        if self.encoder not in ENCODERS or self.encoder_stride not in (8, 16, 32):
            raise ValueError(f"UNetConfig: encoder must be one of {ENCODERS} and encoder_stride 8, 16 or 32, "
                             f"got {self.encoder!r}, {self.encoder_stride!r}")
        if self.res_blocks < 0 or self.encoder_convs < 0 or self.in_channels < 1:
            raise ValueError(
                "UNetConfig: res_blocks and encoder_convs must be >= 0 and in_channels >= 1, got "
                f"res_blocks={self.res_blocks}, encoder_convs={self.encoder_convs}, "
                f"in_channels={self.in_channels}"
            )

    @property
    def depth(self) -> int:
        """Number of downsamplings by 2 below the heatmap grid."""
        return len(self.channels) - 1

    def to_dict(self) -> dict:
        """Plain-python form (for checkpoints and JSON); the U-Net's leaves the encoder's fields out, as every
        run before them was written."""
        d = dataclasses.asdict(self)
        d["channels"] = list(self.channels)
        if self.encoder == "unet":
            del d["encoder"], d["encoder_stride"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> UNetConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise a ValueError naming them."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"UNetConfig: unknown fields {unknown}; known: {sorted(names)}")
        kwargs: dict[str, Any] = {k: tuple(v) if k == "channels" else v for k, v in d.items()}
        return cls(**kwargs)


def _norm(kind: Norm, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(max(1, channels // 8), channels)
    return nn.Identity()


class ConvNormAct(nn.Sequential):
    """Convolution (no bias when a norm follows), normalization, optional ReLU."""

    def __init__(
        self, cin: int, cout: int, kernel: int = 3, stride: int = 1, padding: int | None = None,
        norm: Norm = "batch", act: bool = True,
    ) -> None:
        pad = (kernel - 1) // 2 if padding is None else padding
        layers: list[nn.Module] = [nn.Conv2d(cin, cout, kernel, stride, pad, bias=norm == "none")]
        if norm != "none":
            layers.append(_norm(norm, cout))
        if act:
            layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)


class ResBlock(nn.Module):
    """Three 3x3 convolutions with an identity shortcut: ``relu(x + f(x))``."""

    def __init__(self, channels: int, norm: Norm) -> None:
        super().__init__()
        self.body = nn.Sequential(
            ConvNormAct(channels, channels, norm=norm),
            ConvNormAct(channels, channels, norm=norm),
            ConvNormAct(channels, channels, norm=norm, act=False),
        )

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(x + self.body(x), inplace=True)


class HeatmapHead(nn.Conv2d):
    """The 1x1 convolution to K heatmaps, run as one matrix product per image on channels_last input.

    oneDNN handles 1x1 convolutions with few output channels poorly on CPU (about 2 GFLOP/s for 16 -> 3
    channels at 64 x 64). On channels_last features the same map is ``W (K, C) @ x (C, h w)``, a strided
    GEMM several times faster, whose result is contiguous ``(N, K, h, w)``: the layout the spatial softmax
    wants. Parameters and results are those of ``nn.Conv2d(C, K, 1)``. Under autocast it computes in
    float32.
    """

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(cin, cout, 1)

    def forward(self, x: Tensor) -> Tensor:
        if torch.is_autocast_enabled(x.device.type):
            # the logits in float32 under autocast: their sub-pixel peaks are the detector's precision
            with torch.autocast(x.device.type, enabled=False):
                return self.forward(x.float())
        if x.ndim == 4 and x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous():
            n, c, h, w = x.shape
            y = torch.matmul(self.weight[:, :, 0, 0], x.reshape(n, c, h * w))
            assert self.bias is not None  # nn.Conv2d(cin, cout, 1) has a bias
            return (y + self.bias[:, None]).reshape(n, -1, h, w)
        return super().forward(x)


class Up(nn.Module):
    """Decoder step: 1x1 conv to the skip's channels at low resolution, nearest x2, add the skip, 3x3 conv."""

    def __init__(self, cin: int, cout: int, norm: Norm) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(cin, cout, 1, bias=False) if cin != cout else nn.Identity()
        self.conv = ConvNormAct(cout, cout, norm=norm)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        return self.conv(F.interpolate(self.reduce(x), scale_factor=2.0, mode="nearest") + skip)


class UNet(nn.Module):
    """U-Net keypoint detector: images ``(N, 3, H, W)`` in [0, 1] -> heatmap logits ``(N, K, h, w)``.

    ``(h, w) = heatmaps.heatmap_size(H, W, config.stride)``; ``H`` and ``W`` must be multiples of the stride.
    Heatmap grids that are not multiples of ``2 ** depth`` are zero-padded at the bottom and right inside the
    network and the logits are cropped back, so any such size works.

    Args:
        num_keypoints: K, number of heatmaps.
        config: architecture; defaults to ``UNetConfig()``.

    Example:
        >>> net = UNet(3).eval()
        >>> net(torch.rand(2, 3, 96, 128)).shape
        torch.Size([2, 3, 48, 64])
    """

    def __init__(self, num_keypoints: int, config: UNetConfig | None = None) -> None:
        super().__init__()
        if isinstance(num_keypoints, bool) or not isinstance(num_keypoints, int) or num_keypoints < 1:
            raise ValueError(f"UNet: num_keypoints must be a positive int, got {num_keypoints!r}")
        cfg = UNetConfig() if config is None else config
        if not isinstance(cfg, UNetConfig):
            raise ValueError(f"UNet: config must be a UNetConfig, got {type(cfg).__name__}")
        self.config = cfg
        self.num_keypoints = num_keypoints
        ch, s, norm = cfg.channels, cfg.stride, cfg.norm
        if s == 1:
            self.stem = ConvNormAct(cfg.in_channels, ch[0], 3, 1, 1, norm=norm)
        else:
            self.stem = ConvNormAct(cfg.in_channels, ch[0], 2 * s, s, s // 2, norm=norm)
        self.down = nn.ModuleList()
        for lo, hi in zip(ch[:-1], ch[1:]):
            layers = [ConvNormAct(lo, hi, 3, 2, 1, norm=norm)]
            layers += [ConvNormAct(hi, hi, norm=norm) for _ in range(cfg.encoder_convs)]
            self.down.append(nn.Sequential(*layers))
        self.bottom = nn.Sequential(*[ResBlock(ch[-1], norm) for _ in range(cfg.res_blocks)])
        self.up = nn.ModuleList([Up(hi, lo, norm) for lo, hi in zip(ch[:-1], ch[1:])][::-1])
        self.head = HeatmapHead(ch[0], num_keypoints)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        # Start from near-uniform heatmaps rather than from the random spikes of a ReLU-scaled head.
        nn.init.normal_(self.head.weight, std=1e-2)

    def forward(self, images: Tensor) -> Tensor:
        """Heatmap logits.

        Args:
            images: ``(N, in_channels, H, W)`` float in [0, 1]; ``H, W`` multiples of ``config.stride``.

        Returns:
            ``(N, K, H / stride, W / stride)`` logits (softmax over the last two dims gives ``P``).
        """
        if not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != self.config.in_channels:
            shape = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
            cin = self.config.in_channels
            raise ValueError(f"UNet: images must have shape (N, {cin}, H, W), got {shape}")
        h, w = heatmap_size(images.shape[-2], images.shape[-1], self.config.stride)
        x = self.stem(images)
        m = 1 << self.config.depth
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph))
        skips = []
        for down in self.down:
            skips.append(x)
            x = down(x)
        x = self.bottom(x)
        for up, skip in zip(self.up, reversed(skips)):
            x = up(x, skip)
        logits = self.head(x)
        if ph or pw:
            logits = logits[..., :h, :w]
        return logits

    def fused(self) -> UNet:
        """An inference copy with every BatchNorm folded into its convolution (same outputs in eval mode).

        Returns:
            A new UNet in eval mode; the original is untouched. Without BatchNorm, an eval-mode copy.
        """
        net = copy.deepcopy(self).eval()
        for mod in net.modules():
            if isinstance(mod, ConvNormAct) and isinstance(mod[1], nn.BatchNorm2d):
                mod[0] = torch.nn.utils.fusion.fuse_conv_bn_eval(cast(nn.Conv2d, mod[0]), mod[1])
                mod[1] = nn.Identity()
        return net


def detect(model: nn.Module, images: Tensor, stride: int | None = None,
           window: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """Run the shared network on every camera image of a batch of frames and read off the 2D detections.

    Args:
        model: maps ``(N, 3, H, W)`` to ``(N, K, h, w)`` logits (a :class:`UNet`).
        images: ``(B, C, 3, H, W)`` float in [0, 1].
        stride: heatmap stride; defaults to ``model.config.stride``.
        window: the mean within this many cells of each heatmap's peak (the read-out's:
            :func:`s3k.readout.window_cells`); 0: the whole heatmap's mean.

    Returns:
        ``(logits (B, C, K, h, w), mean_uv (B, C, K, 2), var (B, C, K))``: the moments of the spatial softmax,
        in image pixels, float64 (:func:`s3k.readout.moments`).
    """
    if not isinstance(images, Tensor) or images.ndim != 5:
        shape = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
        raise ValueError(f"detect: images must have shape (B, C, 3, H, W), got {shape}")
    if stride is None:
        stride = cast(int, model.config.stride)
    B, C = images.shape[:2]
    flat = images.reshape(B * C, *images.shape[2:])
    logits = model(flat)
    logits = logits.reshape(B, C, *logits.shape[1:])
    _probs, mean_uv, var = readout.moments(logits, stride, window)
    return logits, mean_uv, var


def conv_layers(model: nn.Module, images: Tensor) -> list[tuple[nn.Conv2d, torch.Size, torch.Size]]:
    """Every ``nn.Conv2d`` of ``model`` in call order, with the input and output shapes it sees in one forward
    pass on ``images`` (run without gradients)."""
    seen: list[tuple[nn.Conv2d, torch.Size, torch.Size]] = []

    def hook(mod: nn.Conv2d, inp: tuple[Tensor, ...], out: Tensor) -> None:
        seen.append((mod, inp[0].shape, out.shape))

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    try:
        with torch.no_grad():
            model(images)
    finally:
        for h in handles:
            h.remove()
    return seen


def count_conv_flops(model: nn.Module, images: Tensor) -> int:
    """Floating-point operations of the model's convolutions for one forward pass on ``images``.

    Counts ``2 * (C_in / groups) * kH * kW`` per output element of every ``nn.Conv2d`` (a multiply and an
    add per weight), plus one add per output element for a bias; norms, activations, resampling and additions
    are not counted (they are memory bound and small).

    Args:
        model: any module containing ``nn.Conv2d`` layers.
        images: the input of one forward pass, e.g. ``(N, 3, H, W)``.

    Returns:
        The FLOP count as an int.
    """
    total = 0
    for mod, _in_shape, out_shape in conv_layers(model, images):
        kh, kw = mod.kernel_size
        per_out = 2 * (mod.in_channels // mod.groups) * kh * kw + (1 if mod.bias is not None else 0)
        total += per_out * out_shape.numel()
    return total
