"""``s3k.Detector``: a trained detector, one pass or two, as one object that takes synchronized frames of any
size with their cameras and gives the read-out (2D detections, confidences, 3D points, validity).

Every part of s3k that uses a trained model goes through it: evaluate, predict, track, stream, export's
verification, the labelling app's suggestions, the robot loop and validation during training.

- :class:`OnePassDetector`: each view's region (default: the whole image) is resampled to the network's
  input size on the detector's device (:func:`s3k.geometry.warp.crop_images`, the map ``K' = M K``), the
  shared network gives heatmaps, and :func:`s3k.readout.read_out` (with the settings the detector was
  trained with, :class:`s3k.detector.DetectorMeta`) gives detections in the frames' own pixels and 3D
  points in the cameras' world frame.
- :class:`TwoPassDetector`: the coarse detector places the object; every view is cut around the crop
  centre of its coarse keypoints by the run's :class:`s3k.detector.CropRule` (the one centre rule,
  :func:`s3k.detector.crop_rule.crop_centres`), on the device, and the refining detector reads the crops;
  with a rigid layout, a frame whose refining points break it takes the coarse read-out where that holds it.

The network inputs are rounded to 8-bit levels before they are scaled to [0, 1]: both passes were trained
on images stored as 8-bit files, and the same rounding keeps what they see at inference what they saw in
training.

Example:
    >>> det = Detector.load("runs/box")  # doctest: +SKIP
    >>> out = det(frames, cams)  # frames uint8 (B, C, H, W, 3), cams Cameras (C,)  # doctest: +SKIP
    >>> out.X, out.valid  # (B, K, 3) world units, (B, K)  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from s3k.base.choices import Arithmetic, Device, Precision, parse_device
from s3k.base.errors import UserError
from s3k.detector.cpu import native_bfloat16_cpu
from s3k.detector.crop_rule import CropRule, crop_centres, is_two_pass, read_two_pass
from s3k.detector.frozen import FrozenNetwork
from s3k.detector.meta import DetectorMeta
from s3k.detector.model_file import load_network, note_uncalibrated
from s3k.geometry import Cameras
from s3k.geometry.warp import (
    crop_images,
    crop_maps,
    metric_crop_boxes,
    region_around,
    regions_around,
    resample_regions,
    resize_crop,
)
from s3k.model import UNet
from s3k.readout import DEFAULT_MIN_WEIGHT, LayoutPrior, ReadOut, coarse_stands_in, read_out

__all__ = ["PRECISIONS", "Detection", "Detector", "OnePassDetector", "TwoPassDetector", "autocast",
           "native_bfloat16", "pick_device", "training_precision"]

PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}
"""The network's precision (autocast); the read-out is float64 whatever the precision."""

Network = Callable[[Tensor], Tensor]
"""Images ``(N, 3, H, W)`` float32 in [0, 1] -> logits ``(N, K, h, w)``."""


def pick_device(name: Device | torch.device = "auto", local_rank: int = 0) -> torch.device:
    """``"auto"`` -> the GPU when available, else the CPU; a CUDA device without a GPU is refused. A name
    is checked here (:func:`s3k.base.choices.parse_device`): the library's entry points pass theirs on."""
    if not isinstance(name, torch.device):
        name = parse_device(name)
    if name == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    device = torch.device(name)
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():  # 0 without CUDA
        raise UserError(f"--device {name}: this machine has no such CUDA GPU", hint="pass --device cpu")
    return device


def native_bfloat16(device: torch.device) -> bool:
    """Whether ``device`` computes bfloat16 natively: a CUDA GPU that supports it, or a CPU whose flags
    include AVX512-BF16 or AMX-BF16 and that PyTorch uses at that level
    (:func:`s3k.detector.cpu.native_bfloat16_cpu`; elsewhere bfloat16 is emulated, slower than float32)."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    return device.type == "cpu" and native_bfloat16_cpu()


def training_precision(name: Precision, device: torch.device) -> Arithmetic:
    """``--precision`` resolved on ``device``: ``"auto"`` is ``"bfloat16"`` where :func:`native_bfloat16`,
    else ``"float32"``."""
    if name == "auto":
        return "bfloat16" if native_bfloat16(device) else "float32"
    return name


def autocast(device: torch.device, precision: Arithmetic):
    """The autocast context of ``precision`` (a key of :data:`PRECISIONS`) on ``device``; a no-op for
    float32."""
    dtype = PRECISIONS[precision]
    return torch.autocast(device.type, dtype=dtype) if dtype is not None else contextlib.nullcontext()


@dataclass
class Detection(ReadOut):
    """A :class:`s3k.readout.ReadOut` in the frames' own pixels, plus how the detector saw them.

    ``confidence`` (beside ``weights``, the paper's weights the points are triangulated with) is the run's
    calibrated confidence: about that share of views lie within two target widths of the truth
    (docs/method.md#confidence); what thresholds compare.

    Attributes:
        pixel_maps: ``(B, C, 3, 3)`` maps from each frame's pixels to the (last) network's input pixels.
        inputs: ``(B, C, 3, h, w)`` the (last) network's inputs in [0, 1], kept with ``keep_heatmaps``.
        coarse: a two-pass detector's coarse read-out (None for one pass).
        placed: ``(B,)`` bool, a two-pass detector's coarse pass placed a keypoint (else the crops were cut
            around the workspace centre); None for one pass.
        fallback: ``(B,)`` bool, a rigid two-pass detector's refining points broke the object's layout and
            the coarse read-out (as it placed the crops: every view weighted) stands in for the frame
            (:func:`s3k.readout.coarse_stands_in`); None for one pass.
        input_size: ``(w, h)`` of the (last) network's input.
    """

    pixel_maps: Tensor | None = None
    inputs: Tensor | None = None
    coarse: ReadOut | None = None
    placed: Tensor | None = None
    fallback: Tensor | None = None
    input_size: tuple[int, int] = (0, 0)

    def network_cameras(self) -> Cameras:
        """The cameras ``(B, C)`` of the (last) network's input pixels: ``K' = M K``."""
        if self.pixel_maps is None:
            return self.cams
        cams = self.cams
        return Cameras(self.pixel_maps.to(cams.dtype) @ cams.K, cams.dist, cams.R, cams.t)

    def to(self, device: torch.device | str) -> Detection:
        """The same detection with every tensor on ``device``."""
        moved: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            moved[f.name] = v.to(device) if isinstance(v, (Tensor, Cameras)) else v
        if isinstance(self.coarse, ReadOut):
            moved["coarse"] = self.coarse.cpu() if torch.device(device).type == "cpu" else self.coarse
        return Detection(**moved)

    def cpu(self) -> Detection:  # type: ignore[override]
        return self.to("cpu")


def _views(images: Any, cameras: int | None = None) -> tuple[list[Tensor], bool]:
    """``(per camera uint8 (B, H_c, W_c, 3), single frame)`` from ``(B, C, H, W, 3)``, one frame ``(C, H, W,
    3)``, or a sequence of ``C`` arrays ``(B, H_c, W_c, 3)`` (cameras of different sizes).

    Raises:
        UserError: frames that are not uint8 (float frames in [0, 1] read as near black), or a sequence
            that reads as ``C`` cameras' frames and as ``B`` frames of ``C`` cameras alike (``cameras`` of
            them, each ``(cameras, H, W, 3)``).
    """
    if isinstance(images, (list, tuple)):
        views = [torch.as_tensor(np.ascontiguousarray(v) if isinstance(v, np.ndarray) else v) for v in images]
        single = False
        shapes = {tuple(v.shape) for v in views}
        if (cameras is not None and cameras > 1 and len(views) == cameras and len(shapes) == 1
                and views[0].ndim == 4 and views[0].shape[0] == cameras):
            raise UserError(
                f"images: a list of {cameras} arrays of shape {tuple(views[0].shape)} reads both as "
                f"{cameras} cameras' frames and as {cameras} frames of {cameras} cameras",
                hint="pass one array (B, C, H, W, 3), e.g. np.stack(frames) for a list of frames")
    else:
        x = torch.as_tensor(np.ascontiguousarray(images) if isinstance(images, np.ndarray) else images)
        single = x.ndim == 4
        if single:
            x = x[None]
        if x.ndim != 5 or x.shape[-1] != 3:
            raise ValueError(f"images: expected (B, C, H, W, 3) or (C, H, W, 3), got {tuple(x.shape)}")
        views = list(x.unbind(1))
    for v in views:
        if v.ndim != 4 or v.shape[-1] != 3:
            raise ValueError(f"images: each camera's frames must be (B, H, W, 3), got {tuple(v.shape)}")
        if v.dtype != torch.uint8:
            raise UserError(f"images: {str(v.dtype).replace('torch.', '')} frames; the detector reads uint8 "
                            "RGB frames with values 0-255",
                            hint="convert them, e.g. (frames * 255).round().astype(np.uint8) for floats in "
                                 "[0, 1]")
    if len({len(v) for v in views}) != 1:
        raise ValueError("images: every camera needs the same number of frames")
    return views, single


SIZE_RATIO = 1.5
"""Frames at least this many times (or at most its inverse) the size their cameras' centred principal point
describes are refused (:func:`_check_sizes`)."""


def _check_sizes(views: list[Tensor], cams: Cameras) -> None:
    """Refuse frames whose size disagrees with their cameras' intrinsics: a principal point that sits at
    about the same fraction of the frame in both axes (the two ratios within 25%: calibrated principal points
    lie a few percent off the centre), as the centre of an image :data:`SIZE_RATIO` times larger or smaller
    does (frames resized, or cameras of the full frames given with resized ones). A crop of a frame whose
    principal point falls there too is refused as well: :attr:`Detector.check_frames` turns the check off.

    Raises:
        UserError: naming the camera, the frame size and the size its intrinsics describe.
    """
    pp = cams.K[..., :2, 2].reshape(-1, len(views), 2).mean(dim=0).cpu()  # (C, 2)
    for c, v in enumerate(views):
        H, W = int(v.shape[1]), int(v.shape[2])
        cx, cy = float(pp[c, 0]), float(pp[c, 1])
        if cx <= 0 or cy <= 0:
            continue
        su, sv = W / (2 * cx + 1), H / (2 * cy + 1)
        s = (su + sv) / 2
        if abs(su - sv) <= 0.25 * s and (min(su, sv) >= SIZE_RATIO or max(su, sv) <= 1 / SIZE_RATIO):
            raise UserError(
                f"images: camera {c}'s frames are {W}x{H} px but its intrinsics (principal point "
                f"{cx:.1f}, {cy:.1f}) describe {2 * cx + 1:.0f}x{2 * cy + 1:.0f} px frames ({s:.2g}x)",
                hint="resize the frames to the calibration's size, or give the cameras of these frames (K' = "
                     "M K, s3k.geometry.warp); set detector.check_frames = False to use them as they are")


def _whole_images(views: list[Tensor]) -> Tensor:
    """``(C, 4)`` boxes of the whole image of every camera (pixel edge coordinates)."""
    return torch.tensor([[0.0, 0.0, v.shape[2], v.shape[1]] for v in views], dtype=torch.float64)


class _Pass:
    """One network with its meta: images of the network's input size -> logits, on ``device``."""

    def __init__(self, net: Network, meta: DetectorMeta, device: torch.device,
                 precision: Arithmetic = "float32", fast: bool = True):
        if precision not in PRECISIONS:
            raise UserError(f"precision {precision!r}: expected one of {', '.join(PRECISIONS)}")
        self.net, self.meta, self.device, self.precision = net, meta, device, precision
        self.fast = fast
        self.run = FrozenNetwork(net, device, fast)  # the same network, frozen where that is exact

    @property
    def size(self) -> tuple[int, int]:
        return int(self.meta.image_size[0]), int(self.meta.image_size[1])

    def cut(self, views: list[Tensor], boxes: Tensor, crops: bool = False) -> tuple[Tensor, bool]:
        """``(inputs, as_they_are)``: network inputs ``(B, C, 3, h, w)`` in [0, 1], 8-bit levels (a
        channels-last view: one copy from the frames), and whether every view was taken whole as it was.

        ``boxes (B, C, 4)`` of every view are resampled to the input size on the device, as the training
        images were: ``crops``, the refining pass's crops (:func:`s3k.geometry.warp.crop_images`); else the
        region's view resized as the dataset resizes its images (:func:`s3k.geometry.warp.resize_crop` on
        the CPU, its area-averaging equivalent :func:`s3k.geometry.warp.resample_regions` elsewhere)."""
        w, h = self.size
        if crops and self.fast and (batched := self._cut_crops(views, boxes)) is not None:
            return batched, False
        out = []  # per camera (B, h, w, 3): stacked, the views of one frame lie together for the network
        as_they_are = True
        for c, v in enumerate(views):
            box = boxes[:, c]
            whole = box.new_tensor([0.0, 0.0, v.shape[2], v.shape[1]])
            if (v.shape[2], v.shape[1]) == (w, h) and bool((box == whole).all()):
                out.append(v.to(self.device, non_blocking=True))
                continue
            as_they_are = False
            if not crops and self.device.type == "cpu" and v.device.type == "cpu":
                # on the CPU, OpenCV's resize of the uint8 frame: what the resized dataset's images were
                frames = v.numpy()
                rows = [resize_crop(frames[b], None, tuple(box[b].tolist()), (w, h))[0]
                        for b in range(len(v))]
                out.append(torch.from_numpy(np.stack(rows)))
                continue
            v, box = region_around(v, box, (w, h))
            x = v.to(self.device, non_blocking=True).permute(0, 3, 1, 2).float()
            warp = crop_images if crops else resample_regions
            out.append(warp(x, box.to(self.device, torch.float32), (w, h)).round_().clamp_(0, 255)
                       .permute(0, 2, 3, 1))
        x = torch.stack([o.float() if o.dtype != torch.float32 else o for o in out], 1).div_(255.0)
        return x.permute(0, 1, 4, 2, 3), as_they_are  # (B, C, 3, h, w), channels last in memory

    def _cut_crops(self, views: list[Tensor], boxes: Tensor) -> Tensor | None:
        """:meth:`cut`'s crops of every view in one resampling, from regions of one size
        (:func:`s3k.geometry.warp.regions_around`); None where the views cannot share one."""
        w, h = self.size
        cut = regions_around(views, boxes, (w, h))
        if cut is None:
            return None
        regions, moved = cut
        B, C = regions.shape[:2]
        x = regions.to(self.device, non_blocking=True).flatten(0, 1).permute(0, 3, 1, 2).float()
        crops = crop_images(x, moved.flatten(0, 1).to(self.device, torch.float32), (w, h))
        x = crops.round_().clamp_(0, 255).permute(0, 2, 3, 1).contiguous().div_(255.0)  # (B C, h, w, 3)
        return x.reshape(B, C, h, w, 3).permute(0, 1, 4, 2, 3)  # (B, C, 3, h, w), channels last in memory

    def logits(self, x: Tensor) -> Tensor:
        """``(B, C, 3, h, w)`` -> ``(B, C, K, h', w')`` float32."""
        B, C = x.shape[:2]
        flat = x.flatten(0, 1)  # a view of the channels-last frames
        with autocast(self.device, self.precision):
            logits = self.run(flat.contiguous(memory_format=torch.channels_last))
        return logits.float().reshape(B, C, *logits.shape[1:])


class Detector:
    """A trained detector (module docstring). Use :meth:`load`; call it on frames.

    Attributes:
        keypoints: keypoint names, in the order of the outputs.
        units: world units of the calibration it was trained with.
        meta: the (refining) network's :class:`s3k.detector.DetectorMeta`.
        device: where it computes.
    """

    meta: DetectorMeta
    device: torch.device
    run: Path | None = None
    """The run folder it was loaded from (None: built in memory), for messages."""
    check_frames: bool = True
    """Refuse whole frames whose size disagrees with the cameras' intrinsics (:func:`_check_sizes`); off for
    crops, whose principal point may lie anywhere."""

    @staticmethod
    def load(run: str | Path, device: Device | torch.device = "auto", precision: Arithmetic = "float32",
             checkpoint: str | None = None, fast: bool = True) -> Detector:
        """The detector of a run folder of ``s3k train`` (one pass or ``--two-pass``), in eval mode, its
        BatchNorm folded into the convolutions (the same function, fewer operations).

        Args:
            run: the run folder.
            device: ``"auto"`` (the GPU when there is one), ``"cpu"``, ``"cuda"``, ...
            precision: the networks' precision: ``float32``, ``bfloat16`` or ``float16`` (autocast).
            checkpoint: a file in a one-pass run folder to load instead of its final model.
            fast: the fast CPU path (:class:`OnePassDetector`); False: the plain one, for comparison.
        """
        dev = pick_device(device)
        detector: Detector
        if is_two_pass(run):
            rule, coarse, fine = read_two_pass(run)
            detector = TwoPassDetector(OnePassDetector.from_run(coarse, dev, precision, fast=fast),
                                       OnePassDetector.from_run(fine, dev, precision, fast=fast), rule)
        else:
            detector = OnePassDetector.from_run(run, dev, precision, checkpoint, fast)
        detector.run = Path(run)
        return detector

    @property
    def keypoints(self) -> list[str]:
        return list(self.meta.keypoints)

    @property
    def units(self) -> str:
        return self.meta.units

    @property
    def frame_meta(self) -> DetectorMeta:
        """The meta of the network that sees whole frames (a two-pass detector's coarse pass): its
        ``geometry`` is the part of each camera's frame the detector was trained on."""
        return self.meta

    @property
    def input_size(self) -> tuple[int, int]:
        """``(W, H)`` the first network's input: frames of this size need no resampling by a one-pass
        detector."""
        raise NotImplementedError

    def __call__(self, images: Any, cams: Cameras, boxes: Tensor | np.ndarray | None = None,
                 min_weight: float = DEFAULT_MIN_WEIGHT, keep_heatmaps: bool = False) -> Detection:
        """The read-out of synchronized frames.

        Args:
            images: uint8 frames ``(B, C, H, W, 3)`` (RGB, 0-255), one frame ``(C, H, W, 3)``, or a sequence
                of ``C`` arrays ``(B, H_c, W_c, 3)`` when the cameras' sizes differ; numpy or torch. Other
                dtypes (float frames in [0, 1]) are refused, and so is a sequence of ``C`` arrays of ``C``
                frames of one size (it reads as ``C`` frames too: stack it).
            cams: the cameras ``(C,)`` or ``(B, C)`` in the frames' own pixels: frames of another size than
                the intrinsics describe are refused (:attr:`check_frames`).
            boxes: ``(C, 4)`` or ``(B, C, 4)`` region of each view (pixel edge coordinates) that the
                (first) network sees, resampled to its input; default the whole image.
            min_weight: views whose calibrated confidence (:attr:`Detection.confidence`) is at or below this
                are not triangulated.
            keep_heatmaps: also keep the (last) network's heatmaps and inputs.

        Returns:
            A :class:`Detection` (float64) in the frames' pixels and the cameras' world frame, on the device
            the frames are on (a single frame keeps a batch of one).
        """
        if min_weight > 0 and self.meta.calibration is None and self.run is not None:
            note_uncalibrated(Path(self.run))
        views, _ = _views(images, int(cams.shape[-1]))
        if self.check_frames and boxes is None:
            _check_sizes(views, cams)
        home = views[0].device
        B = len(views[0])
        cams = cams.to(device=self.device, dtype=torch.float64)
        if boxes is None:
            box = _whole_images(views)[None].expand(B, -1, -1)
        else:
            box = torch.as_tensor(np.asarray(boxes) if isinstance(boxes, np.ndarray) else boxes,
                                  dtype=torch.float64)
            box = box[None].expand(B, -1, -1) if box.ndim == 2 else box
        with torch.inference_mode():
            out = self._detect(views, cams, box.to(self.device), min_weight, keep_heatmaps)
        return out if out.X.device == home else out.to(home)

    def _detect(self, views: list[Tensor], cams: Cameras, boxes: Tensor, min_weight: float,
                keep: bool) -> Detection:
        raise NotImplementedError


class OnePassDetector(Detector):
    """One network on each view's region (:class:`Detector`).

    ``fast`` (the default): on the CPU in float32 the network runs as a frozen graph
    (:class:`s3k.detector.frozen.FrozenNetwork`) and a refining pass cuts every view's crop in one
    resampling; ``fast=False`` is the plain path, per module and per camera, for comparison (the same points
    to well under 0.1 mm: tests/detector/test_frozen_network.py, ``benchmarks/inference.py``)."""

    def __init__(self, net: Network, meta: DetectorMeta, device: Device | torch.device = "cpu",
                 precision: Arithmetic = "float32", fast: bool = True) -> None:
        self.device = torch.device(device)
        self.meta = meta
        self.pass_ = _Pass(net, meta, self.device, precision, fast)
        self.readout = meta.readout_config()  # built once: its layout tensor is not rebuilt for every frame

    @classmethod
    def from_run(cls, run: str | Path, device: torch.device, precision: Arithmetic = "float32",
                 checkpoint: str | None = None, fast: bool = True) -> OnePassDetector:
        model, meta = load_network(run, device, checkpoint)
        if isinstance(model, UNet):  # the fast form of the same network
            model = model.fused().to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        return cls(model, meta, device, precision, fast)

    @property
    def input_size(self) -> tuple[int, int]:
        return self.pass_.size

    def _detect(self, views, cams, boxes, min_weight, keep, crops=False, prior=None):
        x, as_they_are = self.pass_.cut(views, boxes, crops)
        maps = crop_maps(boxes, self.pass_.size)
        config = (self.readout if min_weight == self.readout.min_weight
                  else dataclasses.replace(self.readout, min_weight=min_weight))
        # frames of the network's size, whole: the pixel maps are the identity, and the read-out skips them
        ro = read_out(self.pass_.logits(x), cams, self.meta.stride, self.meta.sigma,
                      None if as_they_are else maps, config, keep_heatmaps=keep, prior=prior)
        return Detection(**{f.name: getattr(ro, f.name) for f in fields(ro)}, pixel_maps=maps,
                         inputs=x if keep else None, input_size=self.pass_.size)


class TwoPassDetector(Detector):
    """A coarse detector that places the object and a refining detector on crops around it, cut by
    ``rule`` (:class:`Detector`; module docstring). With a rigid layout, a frame whose refining points break
    it while the coarse points hold it takes the coarse read-out (``coarse_fallback``; ``Detection.fallback``
    says which)."""

    def __init__(self, coarse: OnePassDetector, fine: OnePassDetector, rule: CropRule,
                 coarse_fallback: bool = True) -> None:
        if list(coarse.keypoints) != list(fine.keypoints):
            raise UserError(f"the coarse pass's keypoints {coarse.keypoints} differ from the refining pass's "
                            f"{fine.keypoints}", hint="train both passes on the same dataset")
        if tuple(fine.input_size) != (rule.size, rule.size):
            raise UserError(f"the refining pass takes {fine.input_size} px but the crop rule cuts "
                            f"{rule.size} px", hint="retrain the refining pass on the rule's crops")
        self.coarse, self.fine, self.rule = coarse, fine, rule
        self.coarse_fallback = coarse_fallback
        self.meta, self.device = fine.meta, fine.device

    @property
    def frame_meta(self) -> DetectorMeta:
        return self.coarse.meta

    @property
    def input_size(self) -> tuple[int, int]:
        return self.coarse.input_size

    def _detect(self, views, cams, boxes, min_weight, keep):
        # the coarse heatmaps are kept for the rigid read-out's search: they tell a keypoint the refining
        # views are all unsure of from its mirror image (s3k.readout.LayoutPrior)
        fine = self.fine.readout
        rigid = fine.rigid and fine.layout_search and fine.layout_prior
        coarse = self.coarse._detect(views, cams, boxes, DEFAULT_MIN_WEIGHT, rigid)
        centres, placed = crop_centres(coarse.X, coarse.valid, cams)
        crop_boxes, _ = metric_crop_boxes(cams, centres[:, None, :], self.rule.extent)  # (B, C, 4)
        prior = None
        if rigid:
            prior = LayoutPrior(coarse.probs, coarse.network_cameras(), self.coarse.meta.stride)
        out = self.fine._detect(views, cams, crop_boxes, min_weight, keep, crops=True, prior=prior)
        if fine.rigid and self.coarse_fallback:
            assert fine.layout is not None
            out.fallback = coarse_stands_in(out, coarse, fine.layout, fine.layout_tol)
        coarse.inputs = None
        if not keep:
            coarse.probs = None
        out.coarse, out.placed = coarse, placed
        return out

