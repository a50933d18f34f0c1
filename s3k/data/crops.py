"""The refining pass's data: scale-normalized crops around per-frame 3D estimates, held in memory.

A coarse pass on whole images gives each frame a 3D estimate of the object; :func:`cut_crops` cuts every view
of the full-resolution dataset around the estimate's reprojection, the crop's side covering ``extent`` world
units at the estimate's depth, resampled to ``size`` pixels, and keeps the crops in memory as a
:class:`CropDataset`: the source's frames, splits, keypoints and ground truth, each camera's intrinsics
``K' = M K`` (:mod:`s3k.geometry.warp`). It answers what training asks of a :class:`s3k.data.Dataset`
(frames, labels, calibration, images), so the refining pass trains on it directly; :meth:`CropDataset.write`
saves it as a dataset folder of its own when one is wanted (:func:`write_crop_dataset`). The crops are cut
with the rule the two-pass detector applies at inference (:func:`s3k.geometry.warp.crop_images`).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.data.dataset import Dataset
from s3k.data.protocol import DatasetLike
from s3k.data.writer import DatasetWriter
from s3k.geometry import Cameras, workspace_centre
from s3k.geometry.warp import crop_images, crop_maps, metric_crop_boxes, region_around

__all__ = ["CropCutter", "CropDataset", "cut_crops", "object_centres", "write_crop_dataset"]


def object_centres(points: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The object's 3D estimate per frame: the mean of its finite keypoints (frames with none are left out).

    Args:
        points: ``{frame: (K, 3)}`` keypoints, NaN where unknown (e.g. :func:`s3k.data.tracks_csv.read_csv`).
    """
    out = {}
    for frame, X in points.items():
        X = np.asarray(X, dtype=np.float64)
        ok = np.isfinite(X).all(axis=-1)
        if ok.any():
            out[int(frame)] = X[ok].mean(axis=0)
    return out


class CropDataset:
    """Crops of a dataset's frames, in memory (module docstring); build with :func:`cut_crops`.

    It has the parts of :class:`s3k.data.Dataset`'s interface that training, validation and evaluation use:
    ``frames``, ``split_of``, ``labels``, ``calibration`` (per frame), ``points3d``, ``images``,
    ``cached_images``, ``resized`` (to its own size only); ``path`` is the source dataset's.

    Attributes:
        images_array: ``uint8 (N, C, S, S, 3)`` crops, rows in ``frame_ids`` order.
        maps: ``(N, C, 3, 3)`` float64 maps from source pixels to crop pixels (``K' = M K``).
        extent, size: the crop rule (world units, pixels).
    """

    static_calibration = False

    def __init__(self, source: DatasetLike, frame_ids: np.ndarray, splits: np.ndarray, images: np.ndarray,
                 cams: Cameras, maps: np.ndarray, uv: np.ndarray, mask: np.ndarray,
                 points: tuple[np.ndarray, np.ndarray] | None, keypoints: list[str], extent: float, size: int,
                 description: str | None = None) -> None:
        self.path = Path(source.path)
        self.keypoints, self.cameras, self.units = list(keypoints), list(source.cameras), source.units
        self.skeleton = [p for p in getattr(source, "skeleton", []) if set(p) <= set(keypoints)]
        self.extent, self.size = float(extent), int(size)
        self.image_size = self.source_image_size = (self.size, self.size)
        self.crop_box = (0, 0, self.size, self.size)
        self.description = description
        self.source = {"crops_of": str(source.path), "extent": self.extent, "size": self.size}
        # what a run records of its dataset: the crop rule, not where the source folder lies (moving it
        # does not change the crops)
        self.metadata = {**(source.metadata or {}), "keypoints": self.keypoints, "image_size": [size, size],
                         "calibration": "per_frame", "source": {"extent": self.extent, "size": self.size}}
        self.frame_ids = np.asarray(frame_ids, dtype=np.int64)
        self._splits = np.asarray(splits)
        self.images_array, self.maps = images, maps
        self._cams = cams  # float64 (N, C) crop intrinsics
        self._uv, self._mask, self._points = uv, mask, points
        self._sorted = np.argsort(self.frame_ids, kind="stable")

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __repr__(self) -> str:
        return (f"CropDataset(crops of {str(self.path)!r}, {len(self)} frames, {self.extent:g} {self.units} "
                f"at {self.size} px)")

    def _rows(self, frame_ids) -> np.ndarray:
        ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        pos = np.clip(np.searchsorted(self.frame_ids, ids, sorter=self._sorted), 0, len(self.frame_ids) - 1)
        rows = self._sorted[pos]
        bad = self.frame_ids[rows] != ids
        if bad.any():
            raise KeyError(f"frame ids {ids[bad][:10].tolist()} are not among the crops of {self.path}")
        return rows

    def frames(self, split: str | Sequence[str] | None = None) -> np.ndarray:
        """Frame ids of a split, of several splits one after the other, or all when None."""
        if split is None:
            return self.frame_ids.copy()
        names = [split] if isinstance(split, str) else list(split)
        return np.concatenate([self.frame_ids[:0], *(self.frame_ids[self._splits == n] for n in names)])

    def split_of(self, frame_ids) -> np.ndarray:
        return self._splits[self._rows(frame_ids)]

    def calibration(self, frame_ids, dtype: Any = np.float32) -> Cameras:
        rows = torch.from_numpy(self._rows(frame_ids))
        to = torch.float64 if dtype in (np.float64, torch.float64) else torch.float32
        assert self._cams.dist is not None  # the crops' cameras always carry their distortion
        return Cameras(*(x[rows].to(to).contiguous() for x in (self._cams.K, self._cams.dist, self._cams.R,
                                                                 self._cams.t)))

    def labels(self, frame_ids, dtype: Any = np.float32) -> tuple[np.ndarray, np.ndarray]:
        rows = self._rows(frame_ids)
        return self._uv[rows].astype(dtype), self._mask[rows].copy()

    def points3d(self, frame_ids) -> tuple[np.ndarray, np.ndarray] | None:
        if self._points is None:
            return None
        rows = self._rows(frame_ids)
        return self._points[0][rows].copy(), self._points[1][rows].copy()

    @property
    def has_points3d(self) -> bool:
        return self._points is not None

    def images(self, frame_ids) -> np.ndarray:
        return self.images_array[self._rows(frame_ids)]

    def cached_images(self, frame_ids) -> tuple[np.ndarray, np.ndarray]:
        return self.images_array, self._rows(frame_ids)

    def resized(self, image_size: Sequence[int]) -> CropDataset:
        if tuple(int(v) for v in image_size) != self.image_size:
            raise UserError(f"crops of {self.path} are {self.size} px; they are not resized to "
                            f"{image_size[0]}x{image_size[1]}",
                            hint="leave --image-size at 0 for the refining pass")
        return self

    def write(self, out: str | Path, overwrite: bool = False) -> Path:
        """Save the crops as a dataset folder ``out`` (written beside as ``out.tmp``, then renamed)."""

        out = Path(out)
        if out.exists() and not overwrite:
            raise UserError(f"{out} exists", hint="pass --overwrite to replace it")
        tmp = out.with_name(out.name + ".tmp")
        cal = self._cams.numpy()
        with DatasetWriter(tmp, self.keypoints, self.cameras, self.image_size, self.units,
                           per_frame_calibration=True, overwrite=True, description=self.description,
                           source=self.source) as writer:
            for split in ("labelled", "unlabelled", "test"):
                for row in self._rows(self.frames(split)):
                    labels = None
                    if split != "unlabelled":
                        labels = np.where(self._mask[row][..., None], self._uv[row], np.nan)
                    points = None if self._points is None else np.where(
                        self._points[1][row][:, None], self._points[0][row], np.nan)
                    crop_cams = (cal["K"][row], cal["dist"][row], cal["R"][row], cal["t"][row])
                    writer.add_frame(int(self.frame_ids[row]), split, self.images_array[row], crop_cams,
                                     labels, points3d=points)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
        return out


class CropCutter:
    """Cuts the crops of a dataset's frames batch by batch and gathers them into a :class:`CropDataset`
    (:func:`cut_crops` reads the frames itself; a caller that already holds them, such as the coarse pass's
    estimates, hands them over and spares a second decoding).

    Args:
        source: dataset at full resolution (:class:`s3k.data.Dataset`).
        extent, size, keypoints, fallback: as for :func:`cut_crops`.
    """

    def __init__(self, source: DatasetLike, extent: float, size: int, keypoints: Sequence[str] | None = None,
                 fallback: bool = False) -> None:
        self.ds, self.extent, self.size, self.fallback = source, float(extent), int(size), fallback
        self.names = list(source.keypoints if keypoints is None else keypoints)
        missing = [k for k in self.names if k not in source.keypoints]
        if missing:
            raise UserError(f"{source.path}: no keypoint {missing[0]!r} (it has "
                            f"{', '.join(source.keypoints)})")
        self.kps = [source.keypoints.index(k) for k in self.names]
        self.ids: list[np.ndarray] = []
        self.crops: list[np.ndarray] = []
        self.maps: list[np.ndarray] = []
        self.parts: list[tuple] = []

    def add(self, frames: np.ndarray, centres: Mapping[int, np.ndarray],
            images: np.ndarray | torch.Tensor | None = None) -> None:
        """Cut ``frames`` around their ``centres`` (``{frame: (3,)}``); ``images``: their ``uint8
        (B, C, H, W, 3)`` frames when at hand (read from the dataset otherwise).

        Raises:
            UserError: a frame without a centre when ``fallback`` is off.
        """
        rows = []
        for f in frames:
            if int(f) in centres:
                rows.append(np.asarray(centres[int(f)], dtype=np.float64))
            elif self.fallback:
                rows.append(np.full(3, np.nan))
            else:
                raise UserError(f"frame {int(f)} of {self.ds.path} has no 3D estimate to crop around")
        crops, M, part = _cut_chunk(self.ds, np.asarray(frames), torch.as_tensor(np.stack(rows)), self.kps,
                                    self.extent, self.size, images)
        self.ids.append(np.asarray(frames, dtype=np.int64))
        self.crops.append(crops)
        self.maps.append(M)
        self.parts.append(part)

    def result(self, description: str | None = None) -> CropDataset:
        """The crops cut so far, as a :class:`CropDataset`."""
        ids = np.concatenate(self.ids)
        images = np.ascontiguousarray(np.concatenate(self.crops))
        self.crops.clear()  # the one copy of the crops is the dataset's
        K, dist, R, t, uv, mask = (np.concatenate([p[i] for p in self.parts]) for i in range(6))
        points = None
        if self.ds.has_points3d:
            points = (np.concatenate([p[6] for p in self.parts]), np.concatenate([p[7] for p in self.parts]))
        cams = Cameras(*(torch.from_numpy(np.ascontiguousarray(x)) for x in (K, dist, R, t)))
        return CropDataset(self.ds, ids, self.ds.split_of(ids), images, cams, np.concatenate(self.maps), uv,
                           mask, points, self.names, self.extent, self.size, description)


def cut_crops(source: str | os.PathLike | DatasetLike, centres: Mapping[int, np.ndarray], extent: float,
              size: int, keypoints: Sequence[str] | None = None, *, fallback: bool = False, chunk: int = 32,
              splits: Sequence[str] | None = None, frames: Sequence[int] | None = None,
              description: str | None = None) -> CropDataset:
    """The crops of every frame of ``source`` (a :class:`s3k.data.Dataset` or its folder) around ``centres``.

    Args:
        source: dataset at full resolution.
        centres: ``{frame: (3,)}`` 3D estimate per frame, in the dataset's world units.
        extent: crop side at the estimate's depth, world units.
        size: crop width and height in pixels.
        keypoints: keypoints to keep (default all).
        fallback: cut a frame without an estimate around its rig's workspace centre (where the cameras'
            optical axes meet, :func:`s3k.geometry.workspace_centre`: the detector's rule); without it such a
            frame is an error naming it.
        chunk: frames decoded at once.
        splits: the splits to crop (default all three).
        frames: crop only these frames of those splits (default all).
        description: kept with the crops (and in a written folder's metadata).

    Raises:
        UserError: an unknown keypoint, or a frame without an estimate when ``fallback`` is off.
    """
    ds = Dataset.open(os.fspath(source), cache="none") if isinstance(source, (str, os.PathLike)) else source
    cutter = CropCutter(ds, extent, size, keypoints, fallback)
    ids = np.concatenate([np.asarray(ds.frames(s)) for s in (splits or ("labelled", "unlabelled", "test"))])
    if frames is not None:
        ids = ids[np.isin(ids, np.asarray(list(frames), dtype=np.int64))]
    for start in range(0, len(ids), chunk):
        cutter.add(ids[start:start + chunk], centres)
    return cutter.result(description)


def _cut_chunk(ds: DatasetLike, frames: np.ndarray, centre: torch.Tensor, kps: list[int], extent: float,
               size: int, images: np.ndarray | torch.Tensor | None = None):
    """Crop one batch of frames around ``centre (B, 3)``: ``(uint8 crops, maps M, (K', dist, R, t, labels uv,
    labels mask[, points, points mask]))``; a label outside its crop is left out."""
    if images is None:
        images = ds.images(frames)  # (B, C, H, W, 3) uint8
    cams = ds.calibration(frames, np.float64)
    cal = cams.numpy()
    missing = ~torch.isfinite(centre).all(-1)
    if bool(missing.any()):
        middle, _ = workspace_centre(cams)  # (B, 3)
        centre = torch.where(missing[:, None], middle.to(centre.dtype), centre)
    boxes, _ = metric_crop_boxes(cams, centre[:, None, :], extent)
    B, C = boxes.shape[:2]
    frames_u8 = torch.as_tensor(images)
    crops_u8 = np.empty((B, C, size, size, 3), dtype=np.uint8)
    for b in range(B):
        for c in range(C):  # only the region around the box is made float (as the detector does)
            view, box = region_around(frames_u8[b, c][None], boxes[b, c][None].float(), (size, size))
            crop = crop_images(view.permute(0, 3, 1, 2).float(), box, (size, size))
            crops_u8[b, c] = crop[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()
    M = crop_maps(boxes, (size, size)).numpy()  # (B, C, 3, 3)
    uv, mask = ds.labels(frames, np.float64)
    uv_crop = (np.einsum("bcij,bckj->bcki", M[..., :2, :2], uv) + M[:, :, None, :2, 2])[:, :, kps]
    inside = ((uv_crop >= -0.5) & (uv_crop <= size - 0.5)).all(-1)
    mask = mask[:, :, kps] & inside
    uv_crop = np.where(mask[..., None], uv_crop, 0.0)
    part: tuple = (M @ cal["K"], cal["dist"], cal["R"], cal["t"], uv_crop, mask)
    gt = ds.points3d(frames)
    if gt is not None:
        part += (gt[0][:, kps], gt[1][:, kps])
    return crops_u8, M, part


def write_crop_dataset(source: str | Path, out: str | Path, centres: Mapping[int, np.ndarray], extent: float,
                       size: int, keypoints: Sequence[str] | None = None, *,
                       fallback: bool = False, chunk: int = 32,
                       splits: Sequence[str] | None = None,
                       overwrite: bool = False, description: str | None = None) -> Path:
    """Write the crops of every frame of ``source`` around ``centres`` as a dataset folder ``out``
    (:func:`cut_crops`, then :meth:`CropDataset.write`; the arguments are theirs).

    Returns:
        ``out``.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists", hint="pass --overwrite to replace it")
    crops = cut_crops(source, centres, extent, size, keypoints, fallback=fallback, chunk=chunk, splits=splits,
                      description=description)
    return crops.write(out, overwrite=True)
