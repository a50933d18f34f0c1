"""The crop rule that joins the two passes of a coarse-to-fine detector, and the one crop-centre rule.

A two-pass run folder holds two ordinary runs and the rule that joins them (``RUN/two_pass.json``): every
view of a frame is cut around the reprojection of one 3D centre, the crop's side covering ``extent`` world
units at the centre's depth, and resampled to ``size`` px (:func:`s3k.geometry.warp.metric_crop_boxes`), so
the object has the same size in every crop whatever the camera's distance or focal length.

The centre of a frame is the middle of its coarse keypoints' extent (:func:`extent_middle`: the midpoint of
the two that are farthest apart), not their mean: a mean lies towards where keypoints cluster and can leave
an outlying keypoint at the crop's edge, where a truncated heatmap pulls its estimate inwards. A frame whose
coarse pass placed no keypoint is cut around the rig's workspace centre (:func:`workspace_centre`, where the
cameras' optical axes meet): the same rule at training, evaluation, prediction, tracking and streaming.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.geometry import Cameras, workspace_centre
from s3k.run_folder import RunFolder

__all__ = ["TWO_PASS_FILE", "CropRule", "crop_centres", "extent_middle", "is_two_pass", "read_two_pass",
           "write_two_pass"]

TWO_PASS_FILE = RunFolder.TWO_PASS


@dataclass(frozen=True)
class CropRule:
    """How a frame's crops are cut around its coarse 3D keypoints.

    Attributes:
        extent: side of every crop at the centre's depth, in the dataset's world units.
        size: crop width and height in pixels (the refining network's input).
        margin: the relative margin that went into ``extent`` (recorded for the reader).
    """

    extent: float
    size: int
    margin: float = 0.0


def is_two_pass(run_dir: str | Path) -> bool:
    """Whether ``run_dir`` is a two-pass run folder."""
    return RunFolder(run_dir).is_two_pass()


def read_two_pass(run_dir: str | Path) -> tuple[CropRule, Path, Path]:
    """``(rule, coarse run folder, fine run folder)`` of a two-pass run.

    Raises:
        UserError: the file is missing or a field is absent or of the wrong type.
    """
    path = Path(run_dir) / TWO_PASS_FILE
    try:
        info = json.loads(path.read_text())
        rule = CropRule(float(info["extent"]), int(info["size"]), float(info.get("margin", 0.0)))
        coarse, fine = Path(run_dir) / str(info["coarse"]), Path(run_dir) / str(info["fine"])
    except FileNotFoundError:
        raise UserError(f"{path}: not found (is {run_dir} a run of 's3k train --two-pass'?)") from None
    except (ValueError, KeyError, TypeError) as e:
        raise UserError(f"{path}: not a two-pass run description ({type(e).__name__}: {e})") from None
    if not (rule.extent > 0 and np.isfinite(rule.extent) and rule.size > 0):
        raise UserError(f"{path}: extent {rule.extent} and size {rule.size} must be positive")
    return rule, coarse, fine


def write_two_pass(run_dir: Path, rule: CropRule, coarse_size: int, keypoints) -> None:
    """Write ``RUN/two_pass.json``: the rule, the passes' folders, the coarse size and the keypoints."""
    info = {**asdict(rule), "coarse": RunFolder.COARSE, "fine": RunFolder.FINE, "coarse_size": coarse_size,
            "keypoints": list(keypoints)}
    atomic_write_json(info, run_dir / TWO_PASS_FILE)


def extent_middle(points: np.ndarray) -> np.ndarray | None:
    """The middle of the keypoints' extent: the midpoint of the two finite rows of ``points (K, 3)`` farthest
    apart (the point itself when only one is finite; None when none is).

    Unlike a bounding box in world axes it does not depend on the object's orientation; for three corners of
    a rectangle it is the rectangle's centre, equally far from all of them."""
    X = torch.as_tensor(np.asarray(points, dtype=np.float64))[None]
    centre, placed = _middles(X, torch.isfinite(X).all(-1))
    return centre[0].numpy() if bool(placed[0]) else None


def _middles(X: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`extent_middle` of ``X (B, K, 3)`` where ``valid (B, K)``, batched: ``(centres (B, 3), placed
    (B,))``, the centre 0 where no keypoint is valid."""
    X = torch.where(valid[..., None], X, torch.zeros_like(X))
    d = torch.linalg.vector_norm(X[:, :, None] - X[:, None], dim=-1)  # (B, K, K)
    pair = valid[:, :, None] & valid[:, None, :]
    d = torch.where(pair, d, torch.full_like(d, -1.0))
    K = X.shape[1]
    best = d.flatten(1).argmax(dim=1)
    i, j = best // K, best % K
    rows = torch.arange(len(X), device=X.device)
    return 0.5 * (X[rows, i] + X[rows, j]), valid.any(dim=1)


def crop_centres(X: Tensor, valid: Tensor, cams: Cameras) -> tuple[Tensor, Tensor]:
    """The crop centre of every frame (module docstring): the middle of its valid keypoints' extent, or the
    rig's :func:`workspace_centre` for a frame with none.

    Args:
        X: ``(B, K, 3)`` coarse keypoints (NaN where invalid).
        valid: ``(B, K)`` bool.
        cams: the frames' cameras ``(C,)`` or ``(B, C)``.

    Returns:
        ``(centres (B, 3), placed (B,))``: ``placed`` False where the workspace centre stood in.
    """
    centres, placed = _middles(X, valid & torch.isfinite(X).all(-1))
    if not bool(placed.all()):
        fallback, _ = workspace_centre(cams.to(dtype=centres.dtype, device=centres.device))
        centres = torch.where(placed[:, None], centres, fallback.expand_as(centres))
    return centres, placed
