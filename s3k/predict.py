"""``s3k predict``: per-frame 3D keypoints (with confidence and per-view 2D detections) of a dataset as CSV.

Inference uses only images and calibration: the shared network gives one heatmap per camera and keypoint,
its softmax mean is the 2D detection and its spread the confidence weight ``w`` (DESIGN 1), and the
confidence-weighted triangulation gives the 3D point.

CSV columns (one row per frame and keypoint)::

    frame, keypoint, x, y, z, valid, confidence, u_<cam>, v_<cam>, w_<cam> for every camera

``x, y, z`` are in the dataset's world units (empty when the triangulation is degenerate, ``valid = 0``);
``confidence`` is the mean of the per-view weights ``w``; ``u, v`` are in the dataset's own image pixels
(pixel (0, 0) is the centre of the top-left pixel).
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from s3k.frames import FrameStore, images_to_float
from s3k.geometry import Cameras, project, triangulate_pixels
from s3k.heatmaps import confidence_weight, heatmap_moments, spatial_softmax


@dataclass
class Prediction:
    """Network output for a batch of frames.

    Attributes:
        uv: (B, C, K, 2) per-view 2D detections (softmax means), network-input pixels.
        var: (B, C, K) heatmap variances, squared pixels.
        weight: (B, C, K) confidence weights.
        X: (B, K, 3) confidence-weighted triangulation, world units (zeros where invalid).
        valid: (B, K) triangulation validity.
        reproj: (B, C, K, 2) reprojection of X into every view.
        probs: (B, C, K, h, w) heatmaps (softmax), or None.
    """

    uv: Tensor
    var: Tensor
    weight: Tensor
    X: Tensor
    valid: Tensor
    reproj: Tensor
    probs: Tensor | None = None


@torch.no_grad()
def infer(model: torch.nn.Module, images: Tensor, cams: Cameras, stride: int, sigma: float,
          keep_heatmaps: bool = False) -> Prediction:
    """2D detections, confidences and triangulated 3D keypoints for a batch of frames.

    Args:
        model: network mapping (N, 3, H, W) to (N, K, h, w) logits (eval mode).
        images: (B, C, 3, H, W) float in [0, 1], on the model's device.
        cams: cameras (B, C) of those images.
        stride: heatmap stride.
        sigma: target width in image pixels (for the confidence weight).
        keep_heatmaps: also return the softmax heatmaps.

    Returns:
        A :class:`Prediction` (tensors on the model's device).
    """
    if images.ndim != 5:
        raise ValueError(f"infer: images must be (B, C, 3, H, W), got {tuple(images.shape)}")
    B, C = images.shape[:2]
    logits = model(images.reshape(B * C, *images.shape[2:])).float()
    logits = logits.reshape(B, C, *logits.shape[1:])
    probs = spatial_softmax(logits)
    uv, var = heatmap_moments(probs, stride)
    w = confidence_weight(var, sigma)
    cams = cams.to(device=uv.device, dtype=uv.dtype)
    X, valid = triangulate_pixels(cams, uv, w)
    reproj, _depth = project(cams, X[:, None])
    return Prediction(uv, var, w, X, valid, reproj, probs if keep_heatmaps else None)


def predict_store(model: torch.nn.Module, store: FrameStore, stride: int, sigma: float, batch_size: int = 16,
                  device: str | torch.device = "cpu", keep_heatmaps: bool = False):
    """Run :func:`infer` over every frame of ``store``; yields ``(FrameBatch, Prediction)`` on the CPU."""
    for batch in store.batches(batch_size):
        images = images_to_float(batch.images, device)
        pred = infer(model, images, batch.cams.to(device=device), stride, sigma, keep_heatmaps)
        cpu = Prediction(pred.uv.cpu(), pred.var.cpu(), pred.weight.cpu(), pred.X.cpu(), pred.valid.cpu(),
                         pred.reproj.cpu(), None if pred.probs is None else pred.probs.cpu())
        yield batch, cpu


def pick_device(name: str = "auto", local_rank: int = 0) -> torch.device:
    """'auto' -> the GPU when available, else the CPU."""
    if name == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    return torch.device(name)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--data", required=True, help="dataset folder")
    parser.add_argument("--out", required=True, help="output CSV file")
    parser.add_argument("--split", default="test",
                        help="split to predict: labelled, unlabelled, test, or 'all' (default: test)")
    parser.add_argument("--batch-size", type=int, default=16, help="frames per forward pass (default: 16)")
    parser.add_argument("--device", default="auto", help="'auto', 'cpu', 'cuda' (default: auto)")


def split_frames(dataset, split: str) -> np.ndarray:
    """Frame ids of a split, or of every split for 'all' (in split order, without repeats)."""
    if split != "all":
        return np.asarray(dataset.frames(split))
    ids: list = []
    for s in ("labelled", "unlabelled", "test"):
        try:
            ids.extend(np.asarray(dataset.frames(s)).tolist())
        except (KeyError, ValueError):
            continue
    return np.asarray(list(dict.fromkeys(ids)))


def run(args: argparse.Namespace) -> int:
    from s3k.frames import open_dataset
    from s3k.run import load_detector

    device = pick_device(args.device)
    model, meta = load_detector(args.run, device)
    ds = open_dataset(args.data, meta.image_size)
    if list(ds.keypoints) != list(meta.keypoints):
        print(f"warning: dataset keypoints {ds.keypoints} differ from the model's {meta.keypoints}; "
              "columns use the model's names", file=sys.stderr)
    ids = split_frames(ds, args.split)
    store = FrameStore(ds, ids, preload_mb=0)
    Minv = np.linalg.inv(ds.pixel_map)  # network-input pixels -> stored-image pixels
    cams = list(ds.cameras)
    header = ["frame", "keypoint", "x", "y", "z", "valid", "confidence"]
    for c in cams:
        header += [f"u_{c}", f"v_{c}", f"w_{c}"]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with open(out, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for batch, pred in predict_store(model, store, meta.stride, meta.sigma, args.batch_size, device):
            uv = pred.uv.double().numpy() @ Minv[:2, :2].T + Minv[:2, 2]
            for b, fid in enumerate(batch.frame_ids):
                for k, name in enumerate(meta.keypoints):
                    ok = bool(pred.valid[b, k])
                    xyz = [f"{v:.6g}" for v in pred.X[b, k].tolist()] if ok else ["", "", ""]
                    row = [fid, name, *xyz, int(ok), f"{float(pred.weight[b, :, k].mean()):.4f}"]
                    for c in range(len(cams)):
                        row += [f"{uv[b, c, k, 0]:.3f}", f"{uv[b, c, k, 1]:.3f}",
                                f"{float(pred.weight[b, c, k]):.4f}"]
                    writer.writerow(row)
            n += len(batch.frame_ids)
    print(f"wrote {n} frames x {len(meta.keypoints)} keypoints to {out}")
    return 0
