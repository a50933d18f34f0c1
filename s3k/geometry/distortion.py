"""Lens distortion: OpenCV's 5-term model (k1, k2, p1, p2, k3) on normalized image coordinates
(:func:`distort`) and its Newton inverse (:func:`undistort`); pure torch, batched and differentiable."""

from __future__ import annotations

import torch
from torch import Tensor

from s3k.geometry.shapes import broadcast_shapes, check_last


def distort_terms(x: Tensor, y: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's 5-term model on normalized coords; ``d`` is (..., 5) broadcastable to x[..., None]."""
    k1, k2, p1, p2, k3 = d.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2
    return xd, yd


def _check_dist(xy: Tensor, dist: Tensor, name: str) -> None:
    check_last(f"{name}: xy", xy, (2,), min_ndim=2)
    check_last(f"{name}: dist", dist, (5,))
    broadcast_shapes([f"{name}: xy", f"{name}: dist"], [xy.shape[:-2], dist.shape[:-1]])


def distort(xy: Tensor, dist: Tensor) -> Tensor:
    """Apply OpenCV lens distortion to normalized (undistorted) image coordinates.

    ``x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)`` and likewise for y.

    Args:
        xy: (*, N, 2) normalized coordinates ``(X/Z, Y/Z)``.
        dist: (*, 5) coefficients (k1, k2, p1, p2, k3), one set for all N points; leading dims broadcast.

    Returns:
        (*, N, 2) distorted normalized coordinates.
    """
    _check_dist(xy, dist, "distort")
    xd, yd = distort_terms(xy[..., 0], xy[..., 1], dist[..., None, :])
    return torch.stack([xd, yd], dim=-1)


class _NewtonCoeffs:
    """Distortion coefficients shaped for vector ops on (*, N, 2) points (dist (*, 5))."""

    def __init__(self, dist: Tensor) -> None:
        d = dist[..., None, :]  # (*, 1, 5)
        self.k1, self.k2, self.k3 = d[..., 0:1], d[..., 1:2], d[..., 4:5]
        self.k2x2, self.k3x3 = 2 * self.k2, 3 * self.k3
        self.p = d[..., 2:4]  # (p1, p2)
        self.p_swap = self.p.flip(-1)  # (p2, p1)
        p1, p2 = dist[..., 2], dist[..., 3]
        # The tangential terms' Jacobian, linear in (x, y): xy @ lin gives (6 p2 x + 2 p1 y, 2 p2 x + 6 p1 y).
        self.lin = torch.stack([torch.stack([6 * p2, 2 * p2], -1), torch.stack([2 * p1, 6 * p1], -1)], -2)
        self.p_col = dist[..., 2:4, None]  # xy @ p_col = p1 x + p2 y


def _distort_and_jacobian(xy: Tensor, c: _NewtonCoeffs) -> tuple[Tensor, Tensor, Tensor]:
    """distort(xy) and its symmetric Jacobian [[a, b], [b, c]] as diag (a, c) and off b; for no-grad use.

    Written as few whole-tensor ops as possible: on a few points per frame the cost is per op.
    """
    sq = xy * xy
    r2 = sq.sum(-1, keepdim=True)
    radial = torch.addcmul(c.k1, torch.addcmul(c.k2, c.k3, r2), r2).mul_(r2).add_(1)
    xy_prod = xy[..., :1] * xy[..., 1:]
    f = torch.add(r2, sq, alpha=2).mul_(c.p_swap).addcmul_(xy_prod, c.p, value=2).addcmul_(xy, radial)
    dradial = torch.addcmul(c.k1, torch.addcmul(c.k2x2, c.k3x3, r2), r2)  # d radial / d r2
    diag = torch.addcmul(xy @ c.lin, dradial, sq, value=2).add_(radial)
    off = torch.addcmul(xy @ c.p_col, dradial, xy_prod).mul_(2)
    return f, diag, off


def _newton_step(xy: Tensor, e: Tensor, diag: Tensor, off: Tensor) -> Tensor:
    """xy - J^-1 e for the symmetric 2x2 J; where J is singular (the map folds, far outside any calibrated
    field of view) the point stays put."""
    det = torch.addcmul(diag[..., :1] * diag[..., 1:], off, off, value=-1)
    inv_det = torch.where(det.abs() > 1e-12, 1 / det, 0.0)
    num = torch.addcmul(diag.flip(-1) * e, off, e.flip(-1), value=-1)
    return xy - num * inv_det


def undistort(xy_distorted: Tensor, dist: Tensor, iters: int = 5) -> Tensor:
    """Invert `distort` iteratively, like OpenCV's ``undistortPoints`` but with Newton steps.

    Newton steps from the distorted point itself converge quadratically (OpenCV iterates a fixed point, which
    converges linearly): on realistic lenses 4 steps agree with a converged OpenCV solve to 1e-9 px. The
    gradient is the implicit-function one (one Newton step with autograd from the converged point), so
    backward costs one distortion evaluation regardless of ``iters``.

    Args:
        xy_distorted: (*, N, 2) distorted normalized coordinates.
        dist: (*, 5) coefficients (k1, k2, p1, p2, k3), one set for all N points; leading dims broadcast.
        iters: Newton iterations.

    Returns:
        (*, N, 2) undistorted normalized coordinates.
    """
    _check_dist(xy_distorted, dist, "undistort")
    xy0 = xy_distorted
    with torch.no_grad():
        c = _NewtonCoeffs(dist.detach())
        xs = xy0.detach()
        for _ in range(iters):
            f, diag, off = _distort_and_jacobian(xs, c)
            xs = _newton_step(xs, f - xy0.detach(), diag, off)
    if not (xy_distorted.requires_grad or dist.requires_grad):
        return xs
    # x = x* - J^-1 (f(x*; dist) - x0) with J and x* constant: equals x* in value; its derivative is the
    # implicit one, -J^-1 (df/ddist - dx0/d.), exact at convergence.
    with torch.no_grad():
        _, diag, off = _distort_and_jacobian(xs, c)
    fx, fy = distort_terms(xs[..., 0], xs[..., 1], dist[..., None, :])
    return _newton_step(xs, torch.stack([fx, fy], -1) - xy0, diag, off)
