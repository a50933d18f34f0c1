"""Projection and rays: world points to distorted pixels (:func:`project`), pixels to undistorted pixels
(:func:`undistort_pixels`) and to world-frame rays (:func:`pixel_rays`); pure torch, batched and
differentiable."""

from __future__ import annotations

import torch
from torch import Tensor

from s3k.geometry.cameras import Cameras, camera_centres
from s3k.geometry.distortion import distort_terms, undistort
from s3k.geometry.shapes import broadcast_shapes, check_last

# Normalized image coordinates are clamped to this magnitude in `project` so that points at or behind the
# camera plane (and the polynomial distortion of them) stay finite, even in float32: r^6 * x <= 1e21.
_MAX_NORMALIZED = 1e3
# ... and pixels to this one, so that squaring a residual of such a point stays finite in float32 too.
_MAX_PIXELS = 1e6


def _apply_K(K: Tensor, xy: Tensor) -> Tensor:
    """Pixels from normalized coords: ``K [x, y, 1]``, dehomogenized. K (*, 3, 3), xy (*, N, 2)."""
    Kn = K[..., None, :, :]
    uvw = Kn[..., :, 0] * xy[..., 0:1] + Kn[..., :, 1] * xy[..., 1:2] + Kn[..., :, 2]
    # For any K with last row (0, 0, 1) w == 1 exactly; dividing keeps projective warps exact too.
    return uvw[..., :2] / uvw[..., 2:3]


def _apply_K_inv(K: Tensor, uv: Tensor) -> Tensor:
    """Normalized coords from pixels: ``K^-1 [u, v, 1]`` (general inverse), dehomogenized."""
    return _apply_K(_inverse_3x3(K), uv)


def _inverse_3x3(K: Tensor) -> Tensor:
    """The inverse of ``(*, 3, 3)`` matrices in closed form (adjugate over determinant): a batched LAPACK
    call for a few 3x3 matrices costs more than the rest of a frame's rays."""
    r0, r1, r2 = K.unbind(-2)
    cross = torch.linalg.cross
    adj = torch.stack([cross(r1, r2), cross(r2, r0), cross(r0, r1)], -1)  # columns: K @ adj = det I
    det = (r0 * adj[..., :, 0]).sum(-1)
    return adj / det[..., None, None]


def project(cams: Cameras, X: Tensor, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Project world points into cameras with lens distortion (OpenCV ``projectPoints``).

    Args:
        cams: cameras with leading dims L.
        X: (*L, N, 3) world points; leading dims broadcast against L (e.g. (N, 3) for every camera, or
            (B, 1, N, 3) against cameras (B, C)).
        eps: depth below which a point counts as behind the camera.

    Returns:
        uv: (*L, N, 2) distorted pixel coordinates. Always finite: for points with ``depth <= eps`` the
            divisor is clamped, so their uv is meaningless but safe; mask them with ``depth > eps``.
        depth: (*L, N) camera-frame z.

    Example:
        >>> cams = Cameras(torch.eye(3), None, torch.eye(3), torch.zeros(3))
        >>> project(cams, torch.tensor([[0.5, 0.0, 2.0]]))[0]
        tensor([[0.2500, 0.0000]])
    """
    check_last("project: X", X, (3,), min_ndim=2)
    if X.dtype != cams.dtype:
        raise ValueError(f"project: X dtype {X.dtype} differs from the cameras' {cams.dtype}")
    broadcast_shapes(["project: X", "cameras"], [X.shape[:-2], cams.shape])
    assert cams.dist is not None
    Xc = X @ cams.R.transpose(-1, -2) + cams.t[..., None, :]
    depth = Xc[..., 2]
    xy = Xc[..., :2] / depth.clamp(min=eps)[..., None]
    xy = xy.clamp(-_MAX_NORMALIZED, _MAX_NORMALIZED)
    if cams.dist.device.type != "cpu" or _needs_undistort(cams.dist):  # zero terms leave xy as it is
        xd, yd = distort_terms(xy[..., 0], xy[..., 1], cams.dist[..., None, :])
        xy = torch.stack([xd, yd], dim=-1)
    uv = _apply_K(cams.K, xy).clamp(-_MAX_PIXELS, _MAX_PIXELS)
    return uv, depth


def _needs_undistort(dist: Tensor) -> bool:
    return dist.requires_grad or bool(torch.any(dist != 0))


def undistort_pixels(cams: Cameras, uv: Tensor, iters: int = 5) -> Tensor:
    """Remove lens distortion from pixel coordinates, keeping the same K (``cv2.undistortPoints(..., P=K)``).

    Args:
        cams: cameras with leading dims L.
        uv: (*L, N, 2) distorted pixels; leading dims broadcast against L.
        iters: Newton iterations of `undistort`.

    Returns:
        (*L, N, 2) undistorted pixels.
    """
    check_last("undistort_pixels: uv", uv, (2,), min_ndim=2)
    broadcast_shapes(["undistort_pixels: uv", "cameras"], [uv.shape[:-2], cams.shape])
    assert cams.dist is not None
    if not _needs_undistort(cams.dist):
        return uv + torch.zeros_like(cams.t[..., None, :2])
    xy = undistort(_apply_K_inv(cams.K, uv), cams.dist, iters=iters)
    return _apply_K(cams.K, xy)


def pixel_rays(cams: Cameras, uv: Tensor, iters: int = 5) -> tuple[Tensor, Tensor]:
    """World-frame rays through (distorted) pixels.

    The pixel is undistorted, then ``d = normalize(R^T [x, y, 1])`` with ``(x, y)`` from the general ``K^-1``;
    the origin is the camera centre ``-R^T t``.

    Args:
        cams: cameras with leading dims L.
        uv: (*L, N, 2) distorted pixels; leading dims broadcast against L.
        iters: Newton iterations of `undistort`.

    Returns:
        origins: (*L, N, 3) camera centres (expanded over N).
        directions: (*L, N, 3) unit directions in the world frame.
    """
    check_last("pixel_rays: uv", uv, (2,), min_ndim=2)
    lead = broadcast_shapes(["pixel_rays: uv", "cameras"], [uv.shape[:-2], cams.shape])
    assert cams.dist is not None
    xy = _apply_K_inv(cams.K, uv)
    if _needs_undistort(cams.dist):
        xy = undistort(xy, cams.dist, iters=iters)
    d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
    d = d_cam @ cams.R  # row-vector form of R^T d_cam
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    n = uv.shape[-2]
    d = d.expand(lead + (n, 3))
    origins = camera_centres(cams)[..., None, :].expand(lead + (n, 3))
    return origins, d
