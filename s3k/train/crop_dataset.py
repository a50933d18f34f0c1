"""The refining pass's data: a dataset of scale-normalized crops around per-frame 3D estimates.

A coarse pass on whole images gives each frame a 3D estimate of the object; this module cuts every view of
the full-resolution dataset around the estimate's reprojection, the crop's side covering ``extent`` world
units at the estimate's depth, resamples it to ``size`` pixels and writes the crops as a dataset of their
own: same frames, splits, keypoints and ground truth, each camera's intrinsics ``K' = M K``
(:mod:`s3k.geometry.warp`). A detector trained on it with the ordinary S3K losses, and evaluated on the
crops of test frames made by the same rule, is the second pass of a coarse-to-fine detector; its triangulated
points are in world coordinates, so its metrics are the two-pass detector's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from s3k.errors import UserError

__all__ = ["object_centres", "write_crop_dataset"]


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


def write_crop_dataset(source: str | Path, out: str | Path, centres: Mapping[int, np.ndarray], extent: float,
                       size: int, keypoints: Sequence[str] | None = None, *,
                       fallback: bool = False, chunk: int = 32,
                       splits: Sequence[str] | None = None,
                       overwrite: bool = False, description: str | None = None) -> Path:
    """Write the crops of every frame of ``source`` around ``centres`` as a dataset at ``out``.

    Args:
        source: dataset folder at full resolution.
        out: new dataset folder (written beside as ``out.tmp`` and renamed when complete).
        centres: ``{frame: (3,)}`` 3D estimate per frame, in the dataset's world units.
        extent: crop side at the estimate's depth, world units.
        size: crop width and height in pixels.
        keypoints: keypoints to keep (default all).
        fallback: cut a frame without an estimate around its rig's workspace centre (where the cameras'
            optical axes meet, :func:`s3k.geometry.workspace_centre`: the detector's rule); without it such a
            frame is an error naming it.
        chunk: frames per batch.
        splits: the splits to crop (default all three); the others are left out of ``out``.
        overwrite: replace ``out`` if it exists.
        description: stored in the new dataset's metadata.

    Returns:
        ``out``.
    """
    import os
    import shutil

    import torch

    from s3k.data import Dataset, DatasetWriter

    out = Path(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists", hint="pass --overwrite to replace it")
    ds = Dataset.open(source, cache="none")
    names = list(ds.keypoints if keypoints is None else keypoints)
    missing = [k for k in names if k not in ds.keypoints]
    if missing:
        raise UserError(f"{source}: no keypoint {missing[0]!r} (it has {', '.join(ds.keypoints)})")
    kps = [ds.keypoints.index(k) for k in names]
    tmp = out.with_name(out.name + ".tmp")
    source_meta = {"crops_of": str(source), "extent": extent, "size": size}
    with DatasetWriter(tmp, names, ds.cameras, (size, size), ds.units, per_frame_calibration=True,
                       overwrite=True, description=description, source=source_meta) as writer:
        for split in splits or ("labelled", "unlabelled", "test"):
            ids = np.asarray(ds.frames(split))
            for start in range(0, len(ids), chunk):
                frames = ids[start:start + chunk]
                rows = []
                for f in frames:
                    if int(f) in centres:
                        rows.append(np.asarray(centres[int(f)], dtype=np.float64))
                    elif fallback:
                        rows.append(np.full(3, np.nan))
                    else:
                        raise UserError(f"frame {int(f)} of {source} has no 3D estimate to crop around")
                _write_chunk(writer, ds, split, frames, torch.as_tensor(np.stack(rows)), kps, extent, size)
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out


def _write_chunk(writer, ds, split: str, frames: np.ndarray, centre, kps: list[int], extent: float,
                 size: int) -> None:
    """Crop one batch of frames around ``centre (B, 3)`` and add them to ``writer``."""
    import torch

    from s3k.geometry import workspace_centre
    from s3k.geometry.warp import crop_images, crop_maps, metric_crop_boxes

    images = ds.images(frames)  # (B, C, H, W, 3) uint8
    cams = ds.calibration(frames, np.float64)
    cal = cams.numpy()
    missing = ~torch.isfinite(centre).all(-1)
    if bool(missing.any()):
        middle, _ = workspace_centre(cams)  # (B, 3)
        centre = torch.where(missing[:, None], middle.to(centre.dtype), centre)
    boxes, _ = metric_crop_boxes(cams, centre[:, None, :], extent)
    B, C = boxes.shape[:2]
    flat = torch.as_tensor(images, dtype=torch.float32).reshape(B * C, *images.shape[2:]).permute(0, 3, 1, 2)
    crops = crop_images(flat, boxes.reshape(B * C, 4).float(), (size, size))
    crops_u8 = crops.permute(0, 2, 3, 1).round().clamp(0, 255).to(torch.uint8).numpy()
    crops_u8 = crops_u8.reshape(B, C, size, size, 3)
    M = crop_maps(boxes, (size, size)).numpy()  # (B, C, 3, 3)
    uv, mask = ds.labels(frames)
    uv_crop = np.einsum("bcij,bckj->bcki", M[..., :2, :2], uv.astype(np.float64)) + M[:, :, None, :2, 2]
    gt = ds.points3d(frames)
    for b, frame in enumerate(frames):
        labels = None
        if split != "unlabelled":
            lab = np.where(mask[b][..., None], uv_crop[b], np.nan)[:, kps]
            inside = ((lab >= -0.5) & (lab <= size - 0.5)).all(-1, keepdims=True)
            labels = np.where(inside, lab, np.nan)
        points = None if gt is None else np.where(gt[1][b][kps, None], gt[0][b][kps], np.nan)
        crop_cams = (M[b] @ cal["K"][b], cal["dist"][b], cal["R"][b], cal["t"][b])
        writer.add_frame(int(frame), split, crops_u8[b], crop_cams, labels, points3d=points)
