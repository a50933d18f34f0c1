"""The calibrated confidence: a monotone map from the paper's confidence weight to the share of views whose
detection lies near the truth (docs/method.md#confidence).

The weight ``w`` (:func:`s3k.readout.heatmaps.confidence_weight`) measures a heatmap's spread against the
target width; how right a view with a given weight is depends on the run (a run trained shorter has wider
heatmaps: weights near 0.05 on detections that are right). So each run's weights are calibrated on its own
validation frames at the end of training: :func:`fit_confidence` fits the non-decreasing map ``c(w)`` such
that about a fraction ``c`` of the views given confidence ``c`` lie within ``CALIBRATION_SIGMAS`` target
widths of the truth, in the network's input pixels. Triangulation keeps weighting views by ``w``; thresholds
(the read-out's view selection, the labelling app's accept) compare ``c``.

The fit is an isotonic regression (pool-adjacent-violators) on blocks of at least ``MIN_COUNT`` views of
neighbouring weights, each block's share counted with one pseudo-view within the distance and one beyond, so
that a small validation set gives a coarse map (one block: one confidence for every view) whose values are
never 0 or 1: a threshold of 0 keeps every view, as without a map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["CALIBRATION_SIGMAS", "MIN_COUNT", "RELIABILITY_EDGES", "ConfidenceMap", "fit_confidence",
           "pool_adjacent_violators", "reliability"]

CALIBRATION_SIGMAS = 2.0
"""A view is right when its detection lies within this many target widths of the truth (network-input
pixels): 6 px at the default target width of 3 px, the default ``--outlier-px``."""

MIN_COUNT = 20
"""Fewest views a step of the map is fitted on (fewer views in all: no map)."""

RELIABILITY_EDGES = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
"""Bins of confidence of :func:`reliability`."""


def pool_adjacent_violators(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The non-decreasing sequence nearest to ``values (n,)`` in the least-squares sense weighted by
    ``counts (n,)`` (> 0): adjacent values that decrease are pooled into their weighted mean until none does.

    Example:
        >>> pool_adjacent_violators(np.array([0.1, 0.5, 0.3, 0.9]), np.array([1, 1, 1, 2])).tolist()
        [0.1, 0.4, 0.4, 0.9]
    """
    values = np.asarray(values, dtype=np.float64)
    counts = np.asarray(counts, dtype=np.float64)
    if values.shape != counts.shape or values.ndim != 1:
        raise ValueError(f"pool_adjacent_violators: values and counts must be (n,), got {values.shape} and "
                         f"{counts.shape}")
    means: list[float] = []
    weights: list[float] = []
    sizes: list[int] = []
    for v, c in zip(values.tolist(), counts.tolist()):
        means.append(v)
        weights.append(c)
        sizes.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            c2, c1 = weights.pop(), weights.pop()
            m2, m1 = means.pop(), means.pop()
            means.append((m1 * c1 + m2 * c2) / (c1 + c2))
            weights.append(c1 + c2)
            sizes.append(sizes.pop() + sizes.pop())
    return np.repeat(np.asarray(means), sizes)


@dataclass(frozen=True)
class ConfidenceMap:
    """A run's calibration: the raw weights ``weights`` (strictly increasing knots) map to ``confidence``
    (non-decreasing, in [0, 1]), linearly between knots and constant beyond the ends.

    Attributes:
        weights, confidence: the knots, one per step of the fit (the mean weight of its views, and the share
            of them within ``within_px``).
        within_px: the distance that counts as right, network-input pixels.
        views: how many views the map was fitted on.
    """

    weights: tuple[float, ...]
    confidence: tuple[float, ...]
    within_px: float
    views: int = 0

    def __post_init__(self) -> None:
        w, c = np.asarray(self.weights, dtype=np.float64), np.asarray(self.confidence, dtype=np.float64)
        if w.ndim != 1 or len(w) < 1 or w.shape != c.shape:
            raise ValueError(f"confidence map: as many weights as confidences, at least one, got {len(w)} "
                             f"and {len(c)}")
        if not (np.isfinite(w).all() and np.isfinite(c).all() and (np.diff(w) > 0).all()
                and (np.diff(c) >= 0).all() and ((c >= 0) & (c <= 1)).all()):
            raise ValueError("confidence map: weights must increase and confidences must not decrease, in "
                             "[0, 1]")
        if not (math.isfinite(self.within_px) and self.within_px > 0):
            raise ValueError(f"confidence map: within_px must be > 0, got {self.within_px}")

    def __call__(self, weights: Tensor) -> Tensor:
        """The calibrated confidence of raw weights ``(*)``, in their dtype and device (NaN stays NaN)."""
        xs = torch.tensor(self.weights, dtype=weights.dtype, device=weights.device)
        ys = torch.tensor(self.confidence, dtype=weights.dtype, device=weights.device)
        if len(xs) == 1:
            out = ys[0].expand_as(weights)
        else:
            i = torch.searchsorted(xs, weights.contiguous(), right=True).clamp_(1, len(xs) - 1)
            x0, x1, y0, y1 = xs[i - 1], xs[i], ys[i - 1], ys[i]
            out = y0 + ((weights - x0) / (x1 - x0)).clamp(0.0, 1.0) * (y1 - y0)
        return torch.where(torch.isnan(weights), weights, out)

    def to_dict(self) -> dict[str, Any]:
        return {"weights": list(self.weights), "confidence": list(self.confidence),
                "within_px": self.within_px, "views": self.views}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ConfidenceMap:
        """The map :meth:`to_dict` wrote (``ValueError``, ``KeyError`` or ``TypeError`` for anything else)."""
        return cls(tuple(float(v) for v in d["weights"]), tuple(float(v) for v in d["confidence"]),
                   float(d["within_px"]), int(d.get("views", 0)))


def _blocks(order_weights: np.ndarray, min_count: int) -> list[slice]:
    """Runs of at least ``min_count`` sorted weights, a run never splitting equal weights (the last run takes
    what is left over)."""
    n = len(order_weights)
    blocks, start = [], 0
    while start < n:
        stop = min(start + min_count, n)
        while stop < n and order_weights[stop] == order_weights[stop - 1]:
            stop += 1
        if n - stop < min_count:
            stop = n
        blocks.append(slice(start, stop))
        start = stop
    return blocks


def fit_confidence(weights: np.ndarray, right: np.ndarray, within_px: float,
                   min_count: int = MIN_COUNT) -> ConfidenceMap | None:
    """The :class:`ConfidenceMap` of views with raw weights ``weights (n,)``, ``right (n,)`` bool where the
    view lies within ``within_px`` of the truth (module docstring); None with fewer than ``min_count`` views
    of finite weight."""
    w = np.asarray(weights, dtype=np.float64).ravel()
    hit = np.asarray(right, dtype=bool).ravel()
    if w.shape != hit.shape:
        raise ValueError(f"fit_confidence: weights and right must have one value per view, got {w.shape} and "
                         f"{hit.shape}")
    keep = np.isfinite(w)
    w, hit = w[keep], hit[keep]
    if len(w) < max(min_count, 1):
        return None
    order = np.argsort(w, kind="stable")
    w, hit = w[order], hit[order]
    blocks = _blocks(w, max(min_count, 1))
    counts = np.array([s.stop - s.start + 2.0 for s in blocks])  # one pseudo-view right and one wrong
    share = np.array([hit[s].sum() + 1.0 for s in blocks]) / counts
    fitted = pool_adjacent_violators(share, counts)
    knots_w, knots_c = [], []
    for value in np.unique(fitted):  # the pooled steps: contiguous, their mean weights increase
        steps = [s for s, f in zip(blocks, fitted) if f == value]
        views = w[steps[0].start:steps[-1].stop]
        knots_w.append(float(views.mean()))
        knots_c.append(float(value))
    return ConfidenceMap(tuple(knots_w), tuple(knots_c), float(within_px), int(len(w)))


def reliability(confidence: np.ndarray, right: np.ndarray,
                edges: tuple[float, ...] = RELIABILITY_EDGES) -> list[dict[str, Any]]:
    """The reliability table of views with confidence ``confidence (n,)`` and ``right (n,)``: per bin of
    ``edges`` (the last bin closed), ``{"from", "to", "views", "confidence" (their mean), "within" (the share
    right)}``, None where the bin is empty."""
    c = np.asarray(confidence, dtype=np.float64).ravel()
    hit = np.asarray(right, dtype=bool).ravel()
    keep = np.isfinite(c)
    c, hit = c[keep], hit[keep]
    rows = []
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = (c >= lo) & ((c <= hi) if i == len(edges) - 2 else (c < hi))
        n = int(sel.sum())
        rows.append({"from": lo, "to": hi, "views": n, "confidence": float(c[sel].mean()) if n else None,
                     "within": float(hit[sel].mean()) if n else None})
    return rows
