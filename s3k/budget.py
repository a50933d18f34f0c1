"""The memory a training needs, estimated from its configuration, against the memory there is.

A model, batch or image that cannot fit in memory is refused before anything is decoded or written, with one
line that names the option to lower. :func:`footprint` estimates the bytes of a training step from the
configuration and the dataset's shape (cameras, keypoints, image size, frames):

- ``weights``: the U-Net's parameters with their gradients and Adam's two moments (16 bytes a parameter,
  float32), plus the teacher's copy with ``--teacher-ema``;
- ``activations``: what one step holds for the backward pass: every convolution's output and its
  normalization's, the additions and upsamplings of the decoder, the logits and the losses' heatmap-sized
  tensors, for ``(batch_labelled + batch_unlabelled) x cameras`` images at the network's input size
  (:func:`activation_elements`, counted per image from the architecture);
- ``images``: the frames held in memory (those that ``--preload-mb`` preloads) and one frame decoded at the
  dataset's own size;
- ``runtime``: what the process takes beyond its tensors once training runs (:data:`RUNTIME`).

The budget is the host's memory: on a GPU the weights and activations live in the device's memory, which
this check does not read (a training there that exceeds it fails at its first step), and ranks of a
data-parallel run on one machine each check the whole machine's memory. The estimate is checked against a
measurement of a real step in ``tests/train/test_budget.py`` (the tensors autograd
saves, and the peak resident memory of a process that runs the step). :func:`check_fits` compares it with
:func:`s3k.base.memory.available_memory`, which honours a control group's limit and ``ulimit -v``.

Example:
    >>> unet_parameters((16, 32, 32, 32), res_blocks=2, stride=2, keypoints=3)
    101171
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from s3k.base.choices import Norm
from s3k.base.errors import UserError
from s3k.base.memory import available_memory
from s3k.geometry.warp import model_image_size

BYTES_PER_PARAMETER = 16
"""float32 weight, gradient and Adam's first and second moments."""
RUNTIME = 256 * 2**20
"""What a training process takes beyond its tensors once it runs: the libraries it loads on first use
(TensorBoard's writer, the convolution kernels' scratch space): what a step of a tiny network on 64 px images
adds to a process's peak resident memory, rounded up."""
SLACK = 1.25
"""The step's transient tensors (gradients of the activations while the backward pass runs, the
augmentation's resampling of the batch) on top of what autograd holds."""


class _Network(Protocol):
    image_size: int
    channels: tuple[int, ...]
    res_blocks: int
    stride: int
    norm: Norm


class _Batches(Protocol):
    batch_labelled: int
    batch_unlabelled: int


class _SelfSupervision(Protocol):
    unsup: bool
    teacher_ema: float


class _Execution(Protocol):
    preload_mb: int


class SizedConfig(Protocol):
    """The sections of :class:`s3k.config.TrainConfig` whose fields size a training."""

    @property
    def model(self) -> _Network: ...
    @property
    def schedule(self) -> _Batches: ...
    @property
    def self_supervision(self) -> _SelfSupervision: ...
    @property
    def execution(self) -> _Execution: ...


@dataclass(frozen=True)
class Footprint:
    """Bytes a training step needs (see the module's docstring); ``parameters`` is a count."""

    parameters: int
    weights: int
    activations: int
    images: int
    runtime: int = RUNTIME

    @property
    def total(self) -> int:
        return self.weights + self.activations + self.images + self.runtime

    def describe(self) -> str:
        """``'about 12.3 GiB (weights and optimizer 0.1, activations 12.0, images 0.2)'``."""
        g = 2.0**30
        return (f"about {_gib(self.total)} GiB (weights and optimizer {self.weights / g:.3g}, activations of "
                f"one step {self.activations / g:.3g}, images {self.images / g:.3g}, runtime "
                f"{self.runtime / g:.3g})")


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g}"


def unet_parameters(channels: Sequence[int], res_blocks: int, stride: int, keypoints: int,
                    norm: Norm = "batch", encoder_convs: int = 0, in_channels: int = 3) -> int:
    """The parameter count of ``s3k.model.UNet(keypoints, UNetConfig(...))``, without building it."""
    ch = [int(c) for c in channels]

    def conv_norm(cin: int, cout: int, kernel: int) -> int:  # ConvNormAct: bias only without a norm
        return cin * cout * kernel * kernel + (cout if norm == "none" else 2 * cout)

    total = conv_norm(in_channels, ch[0], 3 if stride == 1 else 2 * stride)
    for lo, hi in zip(ch[:-1], ch[1:]):
        total += conv_norm(lo, hi, 3) + encoder_convs * conv_norm(hi, hi, 3)
        total += (hi * lo if hi != lo else 0) + conv_norm(lo, lo, 3)  # the decoder's Up
    total += res_blocks * 3 * conv_norm(ch[-1], ch[-1], 3)
    return total + ch[0] * keypoints + keypoints  # the 1x1 heatmap head


def activation_elements(channels: Sequence[int], res_blocks: int, stride: int, keypoints: int,
                        size: tuple[int, int], encoder_convs: int = 0) -> int:
    """float32 values one training image keeps for the backward pass through the U-Net and the losses.

    Every convolution followed by a normalization keeps its output and the normalization's (the ReLU works
    in place); a residual block adds its sum; a decoder step its 1x1 reduction, upsampling and sum. The input
    is held twice (as given and channels-last), the logits and the losses' heatmaps (targets, log-softmax,
    softmax and their products) about six times.
    """
    ch = [int(c) for c in channels]
    w, h = size[0] // stride, size[1] // stride
    m = 1 << (len(ch) - 1)
    area = [(-(-h // m) * m) * (-(-w // m) * m) >> (2 * level) for level in range(len(ch))]  # padded grid
    total = 2 * 3 * size[0] * size[1] + 2 * ch[0] * area[0]  # the input and the stem
    for level in range(1, len(ch)):
        total += 2 * ch[level] * area[level] * (1 + encoder_convs)  # downsampling convolution (+ extras)
        lo = ch[level - 1]
        total += (lo * area[level] if lo != ch[level] else 0) + 4 * lo * area[level - 1]  # Up
    total += res_blocks * 7 * ch[-1] * area[-1]
    return total + 6 * keypoints * w * h


def footprint(cfg: SizedConfig, *, cameras: int, keypoints: int, source_size: tuple[int, int],
              frames: Sequence[int] = ()) -> Footprint:
    """The memory a training of ``cfg`` needs on a dataset of ``cameras`` and ``keypoints`` whose images are
    ``source_size`` (W, H); ``frames`` are the frame counts of the stores a training may preload
    (labelled, unlabelled, validation)."""
    m, b, unsup = cfg.model, cfg.schedule, cfg.self_supervision.unsup
    size = model_image_size(source_size, m.image_size, m.stride)
    parameters = unet_parameters(m.channels, m.res_blocks, m.stride, keypoints, m.norm)
    copies = BYTES_PER_PARAMETER + (4 if unsup and cfg.self_supervision.teacher_ema > 0 else 0)
    images_per_step = (b.batch_labelled + (b.batch_unlabelled if unsup else 0)) * cameras
    per_image = activation_elements(m.channels, m.res_blocks, m.stride, keypoints, size)
    frame = cameras * size[0] * size[1] * 3
    preloaded = sum(n * frame for n in frames if n * frame <= cfg.execution.preload_mb * 2**20)
    decoded = cameras * int(source_size[0]) * int(source_size[1]) * 3
    return Footprint(parameters, parameters * copies, int(SLACK * 4 * per_image * images_per_step),
                     preloaded + decoded + images_per_step * size[0] * size[1] * 3 * 5)


def check_fits(cfg: SizedConfig, *, cameras: int, keypoints: int, source_size: tuple[int, int],
               frames: Sequence[int] = (), where: str | None = None, available: int | None = None) -> None:
    """Refuse a training that cannot fit in memory, naming the option that makes it smaller.

    Args:
        cfg: the configuration.
        cameras, keypoints, source_size, frames: the dataset's shape (see :func:`footprint`).
        where: the dataset folder, named in the message (its ``s3k.json`` gives the image size); None: the
            configuration alone, with the smallest dataset it could train on (:func:`check_config_fits`).
        available: bytes available; default :func:`s3k.base.memory.available_memory`.

    Raises:
        UserError: one line with the estimate, the memory available and the option to lower.
    """
    have = available_memory() if available is None else available
    if have is None:
        return
    need = footprint(cfg, cameras=cameras, keypoints=keypoints, source_size=source_size, frames=frames)
    if need.total <= have:
        return
    parts = {"weights": need.weights, "activations": need.activations, "images": need.images}
    largest = max(parts, key=parts.__getitem__)
    m, b = cfg.model, cfg.schedule
    W, H = int(source_size[0]), int(source_size[1])
    size = model_image_size(source_size, m.image_size, m.stride)
    if largest == "weights":
        hint = (f"lower --channels (now {_listed(m.channels)}) or --res-blocks (now {m.res_blocks}): the "
                f"network has {need.parameters:.3g} parameters")
    elif largest == "images" and cameras * W * H * 3 > have / 2 and where is not None:
        hint = (f"the images of {where} are {W}x{H} px (image_size in {where}/s3k.json): one frame of its "
                f"{cameras} cameras does not fit in memory decoded")
    elif largest == "images":
        hint = f"lower --preload-mb (now {cfg.execution.preload_mb}) or --image-size (now {m.image_size})"
    else:
        shown = (f"now {m.image_size}" if m.image_size or where is None
                 else f"now 0: the dataset's {W}x{H} px")
        hint = (f"lower --image-size ({shown}), --batch-labelled (now {b.batch_labelled})"
                + (f", --batch-unlabelled (now {b.batch_unlabelled})" if cfg.self_supervision.unsup else "")
                + f" or --channels (now {_listed(m.channels)})")
        if where is not None:
            hint += f": {cameras} cameras x {size[0]}x{size[1]} px per frame"
    what = f"training on {where}" if where is not None else "this configuration, on the smallest dataset,"
    raise UserError(f"{what} needs {need.describe()} of memory, {_gib(have)} GiB are available", hint=hint)


def _listed(values: Sequence[int]) -> str:
    return ",".join(map(str, values))


def check_config_fits(cfg: SizedConfig, available: int | None = None) -> None:
    """What the configuration alone refuses: a training that would not fit in memory even on the smallest
    dataset it could train on (two cameras, one keypoint, images of ``image_size x stride`` pixels); the
    dataset's own shape is checked as training starts (:func:`check_fits`)."""
    m = cfg.model
    thin = (max(int(m.image_size), m.stride), m.stride)
    check_fits(cfg, cameras=2, keypoints=1, source_size=thin, available=available)
