"""What the object itself says about a filtered track, as soft constraints on each frame's points.

- **A rigid object** (a run trained with ``--layout-tol`` records its labelled layout,
  :attr:`s3k.detector.DetectorMeta.layout`): the layout's shape (:func:`s3k.readout.layout_shape`) is moved
  onto each frame's points by a weighted Kabsch fit (weights the inverse variances, the shape or its mirror
  image), and each point is drawn towards its place on the moved shape: ``x = (x / v + y / l^2) / (1 / v +
  1 / l^2)`` with ``v`` the point's variance and ``l`` how far the points stand off the layout
  (``layout_std``; by default the median distance over the track, as a per-axis deviation).
- **A skeleton's limbs**: each limb's length is held near its median over the track by minimising
  ``sum_k |x_k - x^_k|^2 / v_k + sum_limbs (|x_i - x_j| - L)^2 / l^2`` (extended position-based dynamics, a
  few iterations per frame): a point placed with little confidence moves more than a confident one. ``l`` is
  the limb's robust spread over the track's detections (``limb_std`` when given).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["hold_limbs", "hold_to_layout", "limb_reference", "weighted_kabsch"]

LIMB_ITERATIONS = 20


def weighted_kabsch(shape: np.ndarray, X: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``shape (K, 3)`` moved onto the points ``X (T, K, 3)`` with weights ``w (T, K)`` (0: not used), the
    shape or its mirror image, whichever fits better: ``(moved (T, K, 3), fitted (T,))``, ``fitted`` where at
    least three keypoints have weight."""
    T = len(X)
    P = np.nan_to_num(X)
    n = w.sum(1, keepdims=True)
    fitted = (w > 0).sum(1) >= 3
    centre = (w[..., None] * P).sum(1) / np.maximum(n, 1e-300)
    best, out = np.full(T, np.inf), np.zeros_like(P)
    for Y in (shape, shape * np.array([1.0, 1.0, -1.0])):
        Yc = (w[..., None] * Y[None]).sum(1) / np.maximum(n, 1e-300)
        A = (Y[None] - Yc[:, None]) * w[..., None]
        H = np.swapaxes(A, 1, 2) @ (P - centre[:, None])
        U, _, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
        D = np.zeros((T, 3, 3))
        D[:, 0, 0] = D[:, 1, 1] = 1.0
        D[:, 2, 2] = np.where(d == 0, 1.0, d)
        R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
        moved = (Y[None] - Yc[:, None]) @ np.swapaxes(R, 1, 2) + centre[:, None]
        cost = (w * ((moved - P) ** 2).sum(-1)).sum(1)
        better = cost < best
        out = np.where(better[:, None, None], moved, out)
        best = np.where(better, cost, best)
    return out, fitted


def hold_to_layout(X: np.ndarray, var: np.ndarray, valid: np.ndarray, shape: np.ndarray,
                   std: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Draw each frame's points towards the rigid ``shape (K, 3)`` moved onto them (module docstring):
    ``(X', var', std)``, ``std`` the layout's deviation used. Frames with fewer than three valid keypoints
    are left as they are."""
    w = np.where(valid, 1.0 / np.maximum(np.nan_to_num(var, nan=np.inf), 1e-300), 0.0)
    moved, fitted = weighted_kabsch(shape, X, w)
    use = valid & fitted[:, None]
    if std is None:
        off = np.linalg.norm(moved - np.nan_to_num(X), axis=-1)[use]
        std = float(np.median(off) / 1.54) if len(off) else 0.0  # median of a 3D norm ~ 1.54 sigma
    if not std > 0:
        return X, var, float(std)
    a, b = 1.0 / np.maximum(var, 1e-300), 1.0 / std**2
    Xn = (X * a[..., None] + moved * b) / (a + b)[..., None]
    return np.where(use[..., None], Xn, X), np.where(use, 1.0 / (a + b), var), float(std)


def limb_reference(X: np.ndarray, edges: Sequence[tuple[int, int]],
                   std: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(L (E,), spread (E,))``: each limb's median length over the frames of ``X (T, K, 3)`` where both ends
    are placed, and its robust spread (``std`` where given); NaN where never placed."""
    L, spread = np.full(len(edges), np.nan), np.full(len(edges), np.nan)
    for e, (i, j) in enumerate(edges):
        d = np.linalg.norm(X[:, i] - X[:, j], axis=-1)
        d = d[np.isfinite(d)]
        if len(d):
            L[e] = np.median(d)
            spread[e] = std if std is not None else max(1.4826 * np.median(np.abs(d - L[e])), 1e-6 * L[e])
    return L, spread


def hold_limbs(X: np.ndarray, var: np.ndarray, valid: np.ndarray, edges: Sequence[tuple[int, int]],
               L: np.ndarray, spread: np.ndarray, iterations: int = LIMB_ITERATIONS) -> np.ndarray:
    """The points of ``X (T, K, 3)`` with each limb held near its length ``L`` (module docstring); ``var``
    ``(T, K)`` the points' variances (how far each may move), ``spread`` each limb's."""
    X = X.copy()
    lam = np.zeros((len(X), len(edges)))
    for _ in range(iterations):
        for e, (i, j) in enumerate(edges):
            if not np.isfinite(L[e]):
                continue
            both = valid[:, i] & valid[:, j]
            d = np.nan_to_num(X[:, i] - X[:, j])
            length = np.linalg.norm(d, axis=-1)
            unit = d / np.maximum(length, 1e-300)[:, None]
            wi, wj = np.nan_to_num(var[:, i]), np.nan_to_num(var[:, j])
            alpha = spread[e] ** 2
            step = (-(length - L[e]) - alpha * lam[:, e]) / np.maximum(wi + wj + alpha, 1e-300)
            step = np.where(both & (length > 0), step, 0.0)
            lam[:, e] += step
            X[:, i] += (wi * step)[:, None] * unit
            X[:, j] -= (wj * step)[:, None] * unit
    return X
