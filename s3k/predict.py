"""``s3k predict``: per-frame 3D keypoints of a dataset, written in the 3D CSV of ``s3k track``.

Inference uses only images and calibration: the shared network gives one heatmap per camera and keypoint, and
:mod:`s3k.readout` turns them into 2D detections, confidence weights and confidence-weighted 3D points (the
same read-out as ``s3k evaluate`` and ``s3k track``). The CSV is anipose's 3D layout
(:mod:`s3k.tracks_csv`): ``fnum`` is the dataset frame id, ``x, y, z`` are in the dataset's world units and
``error`` is in the dataset's own image pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from s3k.data.tables import SPLITS
from s3k.frames import FrameStore, images_to_float
from s3k.geometry import Cameras
from s3k.readout import ReadOut
from s3k.run import DetectorMeta

__all__ = ["PredictSummary", "infer", "pick_device", "predict_dataset", "predict_store", "split_frames"]


@torch.no_grad()
def infer(model: torch.nn.Module, meta: DetectorMeta, images: torch.Tensor, cams: Cameras,
          keep_heatmaps: bool = False, pixel_maps: np.ndarray | None = None) -> ReadOut:
    """2D detections, confidences and triangulated 3D keypoints for a batch of frames.

    Args:
        model: network mapping (N, 3, H, W) to (N, K, h, w) logits (eval mode).
        meta: the detector's description; its read-out (:meth:`s3k.run.DetectorMeta.read_out`) is used.
        images: (B, C, 3, H, W) float in [0, 1], on the model's device.
        cams: cameras (B, C) of those images, or of the original images with ``pixel_maps``.
        keep_heatmaps: also return the softmax heatmaps.
        pixel_maps: see :func:`s3k.readout.read_out`.

    Returns:
        A :class:`s3k.readout.ReadOut` (tensors on the model's device).
    """
    if images.ndim != 5:
        raise ValueError(f"infer: images must be (B, C, 3, H, W), got {tuple(images.shape)}")
    B, C = images.shape[:2]
    logits = model(images.reshape(B * C, *images.shape[2:]))
    logits = logits.reshape(B, C, *logits.shape[1:])
    return meta.read_out(logits, cams, pixel_maps, keep_heatmaps=keep_heatmaps)


def predict_store(model: torch.nn.Module, meta: DetectorMeta, store: FrameStore, batch_size: int = 16,
                  device: str | torch.device = "cpu", keep_heatmaps: bool = False,
                  pixel_map: np.ndarray | None = None):
    """Run :func:`infer` over every frame of ``store``; yields ``(FrameBatch, ReadOut)`` on the CPU.

    (Unannotated so that callers may index ``ReadOut.probs`` they asked for with ``keep_heatmaps``.)

    Results are in the pixels the network saw, or with ``pixel_map`` (``(3, 3)``, the dataset's map from its
    own image pixels to the network's, ``Dataset.pixel_map``) in the dataset's own pixels.
    """
    for batch in store.batches(batch_size):
        images = images_to_float(batch.images, device)
        cams, maps = batch.cams, None
        if pixel_map is not None:
            C = len(store.dataset.cameras)
            maps = np.repeat(np.asarray(pixel_map, dtype=np.float64)[None], C, axis=0)
            Minv = torch.as_tensor(np.linalg.inv(pixel_map), dtype=cams.dtype)
            cams = Cameras(Minv @ cams.K, cams.dist, cams.R, cams.t)  # K = M^-1 K' (an affine map)
        yield batch, infer(model, meta, images, cams.to(device=device), keep_heatmaps, maps).cpu()


def pick_device(name: str = "auto", local_rank: int = 0) -> torch.device:
    """'auto' -> the GPU when available, else the CPU; a device this machine lacks is a one-line error."""
    if name == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    from s3k.errors import UserError

    try:
        device = torch.device(name)
    except RuntimeError:
        raise UserError(f"--device {name!r}: not a device", hint="pass auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():  # 0 without CUDA
        raise UserError(f"--device {name}: this machine has no such CUDA GPU", hint="pass --device cpu")
    return device


def split_frames(dataset, split: str) -> np.ndarray:
    """Frame ids of a split, or of every split for 'all' (labelled, unlabelled, then test frames)."""
    return np.asarray(dataset.frames(SPLITS if split == "all" else split))


@dataclass
class PredictSummary:
    """What :func:`predict_dataset` wrote."""

    path: Path
    frames: int
    keypoints: list[str]
    warnings: list[str]


def predict_dataset(run_dir: str | Path, data: str | Path, out: str | Path, split: str = "test",
                    batch_size: int = 16, device: str = "auto", overwrite: bool = False) -> PredictSummary:
    """Predict the frames of a dataset split and write the 3D CSV (:mod:`s3k.tracks_csv`).

    Args:
        run_dir: run folder of ``s3k train``.
        data: dataset folder.
        out: CSV file to write; never a file of the dataset.
        split: ``labelled``, ``unlabelled``, ``test`` or ``all``.
        batch_size: frames per forward pass.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``...
        overwrite: replace an existing ``out``.

    Raises:
        UserError: ``out`` is a file of the dataset, or exists without ``overwrite``.
    """
    from s3k.frames import open_dataset
    from s3k.run import load_detector
    from s3k.tracks_csv import check_output, csv_rows, write_csv
    from s3k.two_pass import is_two_pass, predict_two_pass

    out = check_output(out, overwrite, dataset=data)
    if is_two_pass(run_dir):
        return predict_two_pass(run_dir, data, out, split, batch_size, device)
    dev = pick_device(device)
    model, meta = load_detector(run_dir, dev)
    ds = open_dataset(data, meta.image_size)
    warnings = []
    if list(ds.keypoints) != list(meta.keypoints):
        warnings.append(f"dataset keypoints {ds.keypoints} differ from the model's {meta.keypoints}; "
                        "columns use the model's names")
    store = FrameStore(ds, split_frames(ds, split), preload_mb=0)
    n = 0
    with write_csv(out, meta.keypoints) as writer:
        for batch, pred in predict_store(model, meta, store, batch_size, dev, pixel_map=ds.pixel_map):
            writer.writerows(csv_rows(batch.frame_ids.tolist(), pred))
            n += len(batch.frame_ids)
    return PredictSummary(out, n, list(meta.keypoints), warnings)
