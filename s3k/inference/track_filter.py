"""Filtered tracks and the frames most in doubt: what ``s3k track`` and ``s3k stream`` do after detection.

- :func:`measurement_std`: each triangulated point's standard deviation in world units, from its detection:
  ``px * hypot(noise_px, error_px) / sqrt(score * ncams / 2)``, with ``px`` the world size of one pixel at the
  point (its depth over the focal length, averaged over the views used), ``error_px`` its reprojection
  residual, ``score`` its mean confidence weight (at least 0.05) and ``ncams`` the views used.
- :func:`filter_track` (offline): the Kalman/RTS smoother of :mod:`s3k.inference.kalman`, then the
  object's constraints of :mod:`s3k.inference.constraints` (a rigid layout, a skeleton's limbs).
- :class:`StreamFilter` (causal): the same frame by frame, from the past only.
- :func:`doubt`: each frame's doubt, as the labelling app ranks frames (``s3k.label.suggest``) but in the
  video's pixels and with the jumps the filter rejected: per keypoint ``(r_w + r_max) / (2 r_med) + (1 -
  mean_c w_c) + REJECTED`` if the filter rejected it, with ``r_w`` the confidence-weighted mean residual
  over the views, ``r_max`` the largest and ``r_med`` the keypoint's median ``r_w`` over the track;
  ``DOUBT_INVALID`` where no point was triangulated; a frame's doubt is the mean over its keypoints.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path, open_text
from s3k.inference.constraints import hold_limbs, hold_to_layout, limb_reference
from s3k.inference.kalman import CausalFilter, FilterSettings, Smoothed, nanmedian, smooth
from s3k.readout.rigid import layout_shape

__all__ = ["DOUBT_COLUMNS", "DOUBT_INVALID", "REJECTED", "StreamFilter", "check_rigid", "doubt", "doubt_path",
           "filter_track", "layout_shape_of", "measurement_std", "raw_path", "read_doubt", "write_doubt"]

DOUBT_INVALID = 100.0
"""A keypoint's doubt where it was not triangulated (as in ``s3k.label.suggest``)."""
REJECTED = 5.0
"""What a jump the filter rejected adds to its keypoint's doubt."""
MIN_SCORE = 0.05


def raw_path(csv_path: str | Path) -> Path:
    """Where ``s3k track`` keeps the unfiltered points beside a filtered CSV: ``<stem>.raw.csv``."""
    p = Path(csv_path)
    return p.with_name(p.stem + ".raw" + (p.suffix or ".csv"))


def doubt_path(csv_path: str | Path) -> Path:
    """Where ``s3k track`` writes its frames ranked by doubt: ``<stem>.doubt.csv``."""
    p = Path(csv_path)
    return p.with_name(p.stem + ".doubt.csv")


def measurement_std(X: np.ndarray, cams: dict[str, np.ndarray], used: np.ndarray, error: np.ndarray,
                    score: np.ndarray, noise_px: np.ndarray | float) -> np.ndarray:
    """``(T, K)`` standard deviation of each point of ``X (T, K, 3)`` (module docstring); ``cams`` the static
    rig as :meth:`s3k.geometry.Cameras.numpy` gives it (``(C, ...)``), ``used (T, C, K)`` the views
    triangulated, ``error``, ``score`` ``(T, K)``, ``noise_px`` a float or ``(K,)``. NaN where ``X`` is."""
    R, t, K = cams["R"], cams["t"], cams["K"]
    depth = np.einsum("cj,tkj->tck", R[:, 2], np.nan_to_num(X)) + t[None, :, 2, None]  # (T, C, K)
    f = np.sqrt(np.abs(K[:, 0, 0] * K[:, 1, 1]))[None, :, None]
    n = used.sum(1)
    px = np.where(n > 0, (np.abs(depth) / f * used).sum(1) / np.maximum(n, 1), (np.abs(depth) / f).mean(1))
    err = np.nan_to_num(error, nan=0.0)
    std = px * np.hypot(noise_px, err) / np.sqrt(np.maximum(score, MIN_SCORE) * np.maximum(n, 1) / 2)
    return np.where(np.isfinite(X).all(-1), std, np.nan)


def layout_shape_of(layout: Any) -> np.ndarray | None:
    """``(K, 3)`` the rigid shape of a run's layout distances (``DetectorMeta.layout``), or None."""
    if layout is None:
        return None


    shape = layout_shape(torch.as_tensor(np.asarray(layout, dtype=np.float64)))
    return None if shape is None else shape.numpy()


def check_rigid(settings: FilterSettings, shape: np.ndarray | None, run: Any = "the run") -> None:
    """Refuse ``--filter-rigid on`` when the run has no rigid layout (``shape`` None, :func:`layout_shape_of`)
    to hold the points to, rather than filter without it."""
    if settings.method != "none" and settings.rigid and shape is None:
        raise UserError(f"--filter-rigid on: {run} has no rigid layout to hold the points to",
                        hint="train it with a rigid object's layout (--layout-tol), or pass --filter-rigid "
                             "auto or off")


def _median_error(error: np.ndarray) -> np.ndarray:
    med = nanmedian(error)
    return np.where(np.isfinite(med), med, 1.0)


def filter_track(X: np.ndarray, error: np.ndarray, score: np.ndarray, used: np.ndarray,
                 cams: dict[str, np.ndarray], settings: FilterSettings, shape: np.ndarray | None = None,
                 edges: Sequence[tuple[int, int]] = ()) -> Smoothed:
    """The offline filter of a track (module docstring): ``X (T, K, 3)`` raw points and their ``error``,
    ``score`` ``(T, K)`` and ``used (T, C, K)``; ``shape`` a rigid layout (:func:`layout_shape_of`),
    ``edges`` the skeleton's limbs as keypoint index pairs. ``info`` of the result records what was used."""
    check_rigid(settings, shape)
    noise_px = settings.noise_px if settings.noise_px is not None else _median_error(error)
    std = measurement_std(X, cams, used, error, score, noise_px)
    out = smooth(X, std, settings)
    info: dict[str, Any] = {"process_noise": out.q.tolist(), "noise_scale": out.s.tolist(),
                            "noise_px": np.broadcast_to(noise_px, (X.shape[1],)).tolist()}
    rigid = settings.rigid if settings.rigid is not None else shape is not None
    if rigid and shape is not None:
        out.X, out.var, info["layout_std"] = hold_to_layout(out.X, out.var, out.valid, shape,
                                                            settings.layout_std)
    if edges:
        L, spread = limb_reference(X, edges, settings.limb_std)  # the detections' own spread
        out.X = hold_limbs(out.X, out.var, out.valid, edges, L, spread)
        info["limbs"] = [{"edge": list(e), "length": float(a), "std": float(b)}
                         for e, a, b in zip(edges, L, spread)]
    info.update(rejected=int(out.rejected.sum()), bridged=int(out.bridged.sum()))
    out.info = info
    return out


@dataclass
class StreamFilter:
    """The causal filter of ``s3k stream`` (module docstring): call it with one frame's detection (a
    :class:`s3k.readout.ReadOut` of one frame) to get ``(X (K, 3), valid (K,), rejected (K,))``. The median
    reprojection residual, the layout's deviation and the limbs' lengths are taken over the frames so far."""

    settings: FilterSettings
    num_keypoints: int
    cams: dict[str, np.ndarray]
    shape: np.ndarray | None = None
    edges: Sequence[tuple[int, int]] = ()

    def __post_init__(self) -> None:
        check_rigid(self.settings, self.shape)
        self.kalman = CausalFilter(self.num_keypoints, self.settings)
        self.errors: list[np.ndarray] = []
        self.placed: list[np.ndarray] = []

    def __call__(self, det: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X = det.X[0].cpu().numpy()[None]
        error, score, used = (det.error[0].cpu().numpy()[None], det.score[0].cpu().numpy()[None],
                              det.used[0].cpu().numpy()[None])
        self.errors.append(error[0])
        noise_px = (self.settings.noise_px if self.settings.noise_px is not None
                    else _median_error(np.stack(self.errors[-256:])))
        std = measurement_std(X, self.cams, used, error, score, noise_px)[0]
        Xf, valid, rejected = self.kalman(X[0], std)
        var = (self.kalman.state.P[:, 0, 0])[None]
        out = Xf[None]
        rigid = self.settings.rigid if self.settings.rigid is not None else self.shape is not None
        if rigid and self.shape is not None:
            out, var, _ = hold_to_layout(out, var, valid[None], self.shape, self.settings.layout_std or None)
        if self.edges:
            self.placed.append(X[0])  # the detections' own spread
            L, spread = limb_reference(np.stack(self.placed[-256:]), self.edges, self.settings.limb_std)
            out = hold_limbs(out, var, valid[None], self.edges, L, spread)
        return out[0], valid, rejected


DOUBT_COLUMNS = ["rank", "fnum", "doubt", "confidence", "residual_px", "worst_view_px", "invalid", "rejected",
                 "worst_keypoint", "rejected_keypoints"]


def doubt(weights: np.ndarray, residual: np.ndarray, valid: np.ndarray,
          rejected: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Each frame's doubt (module docstring) and its parts, from ``weights``, ``residual`` ``(T, C, K)`` (NaN
    where not triangulated), ``valid`` and ``rejected`` ``(T, K)``: ``{"doubt", "confidence",
    "residual_px", "worst_view_px", "invalid", "rejected" (T,), "per_keypoint" (T, K)}``."""
    w, r = weights, np.nan_to_num(residual, nan=0.0)
    weighted = (w * r).sum(1) / np.maximum(w.sum(1), 1e-12)  # (T, K)
    worst = r.max(1)
    scale = nanmedian(np.where(valid, weighted, np.nan))
    scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
    conf = w.mean(1)
    rej = np.zeros_like(valid) if rejected is None else rejected
    per = np.where(valid, (weighted + worst) / (2 * scale) + (1 - conf) + REJECTED * rej, DOUBT_INVALID)
    n = np.maximum(valid.sum(1), 1)
    return {"doubt": per.mean(1), "confidence": conf.mean(1),
            "residual_px": np.where(valid.any(1), (weighted * valid).sum(1) / n, np.nan),
            "worst_view_px": np.where(valid.any(1), np.where(valid, worst, 0).max(1), np.nan),
            "invalid": (~valid).sum(1), "rejected": rej.sum(1), "per_keypoint": per}


def write_doubt(path: str | Path, fnums: Sequence[int], scores: dict[str, np.ndarray],
                keypoints: Sequence[str], rejected: np.ndarray | None = None) -> Path:
    """Write the frames ranked by doubt, worst first (:data:`DOUBT_COLUMNS`), as a CSV."""


    order = sorted(range(len(fnums)), key=lambda i: (-float(scores["doubt"][i]), int(fnums[i])))
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(DOUBT_COLUMNS)
        for rank, i in enumerate(order, 1):
            per = scores["per_keypoint"][i]
            rej = [] if rejected is None else [k for k, r in zip(keypoints, rejected[i]) if r]
            out.writerow([rank, int(fnums[i]), f"{scores['doubt'][i]:.6g}", f"{scores['confidence'][i]:.4f}",
                          f"{scores['residual_px'][i]:.4g}", f"{scores['worst_view_px'][i]:.4g}",
                          int(scores["invalid"][i]), int(scores["rejected"][i]),
                          keypoints[int(np.argmax(per))], ";".join(rej)])
    return path


def _whole(text: str | None) -> bool:
    """Whether ``text`` is a whole number from 0 to 2**63 - 1 in ASCII digits."""
    return re.fullmatch(r"\s*[0-9]{1,19}\s*", text or "") is not None and int(text or "") < 2**63


def read_doubt(path: str | Path) -> list[dict[str, str]]:
    """The rows of a ranking :func:`write_doubt` wrote, worst first.

    Raises:
        UserError: the file is missing or is not such a ranking (naming the file and the column), or a row's
            ``fnum`` or ``rank`` is not a whole number >= 0 or its ``doubt`` not a finite number (naming the
            line).
    """
    try:
        with open_text(path) as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in ("fnum", "doubt") if c not in (reader.fieldnames or [])]
            if missing:
                raise UserError(f"{path}: not a ranking of 's3k track' (no column {missing[0]!r})")
            rows = list(reader)
    except FileNotFoundError:
        raise UserError(f"{path}: no such ranking", hint="run 's3k track' first; it writes <stem>.doubt.csv "
                        "beside its --out") from None
    for line, row in enumerate(rows, 2):
        for column in ("fnum", "rank"):
            text = row.get(column)
            if (column == "rank" and text is None) or _whole(text):
                continue
            raise UserError(f"{path}: line {line}: {column} {text!r} is not a whole number >= 0",
                            hint="run 's3k track' again to write the ranking anew")
        try:
            finite = np.isfinite(float(row.get("doubt") or ""))
        except ValueError:
            finite = False
        if not finite:
            raise UserError(f"{path}: line {line}: doubt {row.get('doubt')!r} is not a finite number",
                            hint="run 's3k track' again to write the ranking anew")
    return sorted(rows, key=lambda r: int(r.get("rank") or 0))
