"""Cameras: the OpenCV pinhole + distortion model, projection, rays and rotations.

Everything here is pure torch, broadcasts over leading dimensions, works in float32 and float64 and is
differentiable. Conventions (docs/architecture.md): ``x_cam = R @ x_world + t``; pixel (0, 0) is the centre
of the top-left pixel, u right, v down; ``K`` is a general 3x3 (skew allowed, so warps ``K <- M @ K`` stay
exact); ``dist = (k1, k2, p1, p2, k3)`` as in OpenCV.

Dimension names: ``L`` the leading dims of a camera set (e.g. ``(C,)`` for a rig, ``(B, C)`` per frame),
``N`` points, ``V`` views of one point.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

# Normalized image coordinates are clamped to this magnitude in `project` so that points at or behind the
# camera plane (and the polynomial distortion of them) stay finite, even in float32: r^6 * x <= 1e21.
_MAX_NORMALIZED = 1e3
# ... and pixels to this one, so that squaring a residual of such a point stays finite in float32 too.
_MAX_PIXELS = 1e6


def _check_last(name: str, x: Tensor, sizes: Sequence[int], min_ndim: int | None = None) -> None:
    """Raise a ValueError naming ``name`` unless ``x`` is a floating tensor ending in ``sizes``."""
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    want = tuple(sizes)
    min_ndim = len(want) if min_ndim is None else min_ndim
    if x.ndim < min_ndim or tuple(x.shape[x.ndim - len(want) :]) != want:
        shape = "(*, " + ", ".join(str(s) for s in want) + ")"
        raise ValueError(f"{name}: expected shape {shape}, got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def _broadcast_shape(*shapes: Sequence[int]) -> torch.Size | None:
    """The broadcast of ``shapes``, or None if they do not broadcast (plain Python: torch's own helper costs
    tens of microseconds, which shows when geometry runs per frame on a handful of points)."""
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    for s in shapes:
        for i, size in enumerate(s, start=ndim - len(s)):
            if size != 1:
                if out[i] not in (1, size):
                    return None
                out[i] = size
    return torch.Size(out)


def _broadcast(names: Sequence[str], shapes: Sequence[Sequence[int]]) -> torch.Size:
    """Broadcast leading shapes, with an error that names the arguments."""
    out = _broadcast_shape(*shapes)
    if out is None:
        desc = ", ".join(f"{n} {tuple(s)}" for n, s in zip(names, shapes))
        raise ValueError(f"leading dimensions do not broadcast: {desc}")
    return out


# ----------------------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(eq=False)
class Cameras:
    """A set of calibrated cameras with arbitrary leading dims ``L``.

    Attributes:
        K: (*L, 3, 3) intrinsics (general 3x3; skew and warped intrinsics allowed).
        dist: (*L, 5) OpenCV distortion (k1, k2, p1, p2, k3). ``None`` means no distortion.
        R: (*L, 3, 3) world->camera rotation, ``x_cam = R @ x_world + t``.
        t: (*L, 3) world->camera translation.

    The four tensors may have leading dims that broadcast against each other (e.g. one ``K`` shared by all
    cameras); they are expanded to the common ``L`` on construction. All must share dtype and device.

    Example:
        >>> eye = torch.eye(3).expand(4, 3, 3)
        >>> cams = Cameras(eye, None, eye, torch.zeros(4, 3))
        >>> cams.shape
        torch.Size([4])
    """

    K: Tensor
    dist: Tensor | None
    R: Tensor
    t: Tensor

    def __post_init__(self) -> None:
        _check_last("Cameras.K", self.K, (3, 3))
        _check_last("Cameras.R", self.R, (3, 3))
        _check_last("Cameras.t", self.t, (3,))
        if self.dist is None:
            self.dist = self.K.new_zeros(self.K.shape[:-2] + (5,))
        _check_last("Cameras.dist", self.dist, (5,))
        fields = {"K": self.K, "dist": self.dist, "R": self.R, "t": self.t}
        for name, x in fields.items():
            if x.dtype != self.K.dtype or x.device != self.K.device:
                raise ValueError(
                    f"Cameras.{name}: dtype/device {x.dtype}/{x.device} differs from "
                    f"Cameras.K {self.K.dtype}/{self.K.device}"
                )
        lead = _broadcast(
            [f"Cameras.{n}" for n in fields],
            [self.K.shape[:-2], self.dist.shape[:-1], self.R.shape[:-2], self.t.shape[:-1]],
        )
        self.K = self.K.expand(lead + (3, 3))
        self.dist = self.dist.expand(lead + (5,))
        self.R = self.R.expand(lead + (3, 3))
        self.t = self.t.expand(lead + (3,))

    @property
    def shape(self) -> torch.Size:
        """The leading dims ``L``."""
        return self.t.shape[:-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.K.dtype

    @property
    def device(self) -> torch.device:
        return self.K.device

    def __len__(self) -> int:
        if len(self.shape) == 0:
            raise TypeError("len() of a single camera (no leading dims)")
        return self.shape[0]

    def __getitem__(self, index: Any) -> Cameras:
        """Index the leading dims, e.g. ``cams[:, 0]`` for camera 0 of every frame of a ``(B, C)`` set."""
        idx = index if isinstance(index, tuple) else (index,)
        if any(i is Ellipsis for i in idx):
            raise ValueError("Cameras[...]: Ellipsis is ambiguous here; index the leading dims explicitly")
        if sum(i is not None for i in idx) > len(self.shape):
            raise ValueError(f"Cameras[{index!r}]: too many indices for leading dims {tuple(self.shape)}")
        assert self.dist is not None
        return Cameras(self.K[idx], self.dist[idx], self.R[idx], self.t[idx])

    def to(self, *args: Any, **kwargs: Any) -> Cameras:
        """Like ``Tensor.to`` (dtype and/or device), applied to every field."""
        assert self.dist is not None
        return Cameras(*(x.to(*args, **kwargs) for x in (self.K, self.dist, self.R, self.t)))

    def reshape(self, *shape: int) -> Cameras:
        """Reshape the leading dims."""
        lead = tuple(shape[0]) if len(shape) == 1 and isinstance(shape[0], (tuple, list)) else shape
        assert self.dist is not None
        return Cameras(
            self.K.reshape(*lead, 3, 3), self.dist.reshape(*lead, 5), self.R.reshape(*lead, 3, 3),
            self.t.reshape(*lead, 3),
        )

    def centres(self) -> Tensor:
        """Camera centres in world coordinates, ``-R^T t``: (*L, 3)."""
        return camera_centres(self)

    def projection_matrices(self) -> Tensor:
        """``P = K [R | t]``: (*L, 3, 4) (ignores distortion)."""
        return self.K @ torch.cat([self.R, self.t[..., None]], dim=-1)

    @classmethod
    def from_numpy(
        cls,
        K: Any,
        dist: Any,
        R: Any,
        t: Any,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> Cameras:
        """Build from array-likes. ``R`` may be (*L, 3, 3) matrices or Rodrigues vectors shaped like ``t``.

        ``dist`` may be ``None`` or have fewer than 5 coefficients (zero padded); more than 5 coefficients are
        accepted only when the extra (rational/thin-prism) terms are zero, since the model here has 5.
        ``t`` of shape (*L, 3, 1), as OpenCV returns it, is accepted.
        """

        def arr(name: str, x: Any) -> Tensor:
            a = np.asarray(x, dtype=np.float64)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Cameras.from_numpy: {name} contains non-finite values")
            return torch.from_numpy(a)  # float64 until the end, so Rodrigues vectors convert exactly

        K_ = arr("K", K)
        t_ = arr("t", t)
        if t_.ndim >= 2 and t_.shape[-2:] == (3, 1):
            t_ = t_[..., 0]
        R_ = arr("R", R)
        # Rodrigues vectors have the shape of t (matrices one more dim): unambiguous even for 3 cameras.
        if R_.ndim >= 2 and R_.shape[-2:] == (3, 1) and R_.shape[:-1] == t_.shape:
            R_ = R_[..., 0]
        if R_.shape == t_.shape:
            R_ = rodrigues_to_matrix(R_)
        if dist is None:
            d = K_.new_zeros(K_.shape[:-2] + (5,))
        else:
            d = arr("dist", dist)
            if d.ndim >= 2 and d.shape[-1] == 1:  # OpenCV's (n, 1) column
                d = d[..., 0]
            if K_.ndim == 2:  # a single camera: accept (n,), (1, n), (n, 1)
                d = d.reshape(-1)
            n = d.shape[-1]
            if n < 5:
                d = torch.cat([d, d.new_zeros(d.shape[:-1] + (5 - n,))], dim=-1)
            elif n > 5:
                if torch.any(d[..., 5:] != 0):
                    raise ValueError(
                        f"Cameras.from_numpy: dist has {n} coefficients with non-zero terms beyond "
                        "(k1, k2, p1, p2, k3); the rational/thin-prism models are not supported"
                    )
                d = d[..., :5]
        return cls(*(x.to(dtype=dtype, device=device) for x in (K_, d, R_, t_)))

    def numpy(self) -> dict[str, np.ndarray]:
        """The fields as float64 NumPy arrays: ``{"K", "dist", "R", "t"}`` with the shapes above."""
        assert self.dist is not None
        fields = {"K": self.K, "dist": self.dist, "R": self.R, "t": self.t}
        return {k: v.detach().cpu().to(torch.float64).numpy().copy() for k, v in fields.items()}


def camera_centres(cams: Cameras) -> Tensor:
    """Camera centres in world coordinates ``a = -R^T t``.

    Args:
        cams: cameras with leading dims L.

    Returns:
        (*L, 3) centres.
    """
    return -(cams.R.transpose(-1, -2) @ cams.t[..., None])[..., 0]


# ----------------------------------------------------------------------------------------------------------
# Distortion
# ----------------------------------------------------------------------------------------------------------


def _distort_terms(x: Tensor, y: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's 5-term model on normalized coords; ``d`` is (..., 5) broadcastable to x[..., None]."""
    k1, k2, p1, p2, k3 = d.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2
    return xd, yd


def _check_dist(xy: Tensor, dist: Tensor, name: str) -> None:
    _check_last(f"{name}: xy", xy, (2,), min_ndim=2)
    _check_last(f"{name}: dist", dist, (5,))
    _broadcast([f"{name}: xy", f"{name}: dist"], [xy.shape[:-2], dist.shape[:-1]])


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
    xd, yd = _distort_terms(xy[..., 0], xy[..., 1], dist[..., None, :])
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
    fx, fy = _distort_terms(xs[..., 0], xs[..., 1], dist[..., None, :])
    return _newton_step(xs, torch.stack([fx, fy], -1) - xy0, diag, off)


# ----------------------------------------------------------------------------------------------------------
# Projection and rays
# ----------------------------------------------------------------------------------------------------------


def _apply_K(K: Tensor, xy: Tensor) -> Tensor:
    """Pixels from normalized coords: ``K [x, y, 1]``, dehomogenized. K (*, 3, 3), xy (*, N, 2)."""
    Kn = K[..., None, :, :]
    uvw = Kn[..., :, 0] * xy[..., 0:1] + Kn[..., :, 1] * xy[..., 1:2] + Kn[..., :, 2]
    # For any K with last row (0, 0, 1) w == 1 exactly; dividing keeps projective warps exact too.
    return uvw[..., :2] / uvw[..., 2:3]


def _apply_K_inv(K: Tensor, uv: Tensor) -> Tensor:
    """Normalized coords from pixels: ``K^-1 [u, v, 1]`` (general inverse), dehomogenized."""
    Kinv = torch.linalg.inv(K)
    return _apply_K(Kinv, uv)


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
    _check_last("project: X", X, (3,), min_ndim=2)
    if X.dtype != cams.dtype:
        raise ValueError(f"project: X dtype {X.dtype} differs from the cameras' {cams.dtype}")
    _broadcast(["project: X", "cameras"], [X.shape[:-2], cams.shape])
    assert cams.dist is not None
    Xc = X @ cams.R.transpose(-1, -2) + cams.t[..., None, :]
    depth = Xc[..., 2]
    xy = Xc[..., :2] / depth.clamp(min=eps)[..., None]
    xy = xy.clamp(-_MAX_NORMALIZED, _MAX_NORMALIZED)
    xd, yd = _distort_terms(xy[..., 0], xy[..., 1], cams.dist[..., None, :])
    uv = _apply_K(cams.K, torch.stack([xd, yd], dim=-1)).clamp(-_MAX_PIXELS, _MAX_PIXELS)
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
    _check_last("undistort_pixels: uv", uv, (2,), min_ndim=2)
    _broadcast(["undistort_pixels: uv", "cameras"], [uv.shape[:-2], cams.shape])
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
    _check_last("pixel_rays: uv", uv, (2,), min_ndim=2)
    lead = _broadcast(["pixel_rays: uv", "cameras"], [uv.shape[:-2], cams.shape])
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


# ----------------------------------------------------------------------------------------------------------
# Rotations
# ----------------------------------------------------------------------------------------------------------


def _skew(v: Tensor) -> Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def rodrigues_to_matrix(rvec: Tensor) -> Tensor:
    """Rotation matrices from axis-angle vectors (``cv2.Rodrigues``), differentiable and safe at 0.

    ``R = I + A [r]x + B [r]x^2`` with ``A = sin(th)/th``, ``B = (1 - cos(th))/th^2 = 2 sin^2(th/2)/th^2``
    (the latter form avoids cancellation); Taylor series for small angles keep value and gradient exact at 0.

    Args:
        rvec: (*, 3) axis * angle (radians).

    Returns:
        (*, 3, 3) rotation matrices.
    """
    _check_last("rodrigues_to_matrix: rvec", rvec, (3,))
    th2 = (rvec * rvec).sum(-1)
    small = th2 < 1e-4
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = th2s.sqrt()
    half = th / 2
    a_big = torch.sin(th) / th
    b_big = 0.5 * (torch.sin(half) / half) ** 2
    # Errors of the truncated series are below th^6/5040 < 2e-16 at th^2 < 1e-4.
    a_small = 1 - th2 / 6 + th2 * th2 / 120
    b_small = 0.5 - th2 / 24 + th2 * th2 / 720
    A = torch.where(small, a_small, a_big)[..., None, None]
    B = torch.where(small, b_small, b_big)[..., None, None]
    S = _skew(rvec)
    eye = torch.eye(3, dtype=rvec.dtype, device=rvec.device)
    return eye + A * S + B * (S @ S)


def matrix_to_rodrigues(R: Tensor) -> Tensor:
    """Axis-angle vectors from rotation matrices (``cv2.Rodrigues``), differentiable, stable near 0 and pi.

    For angles below pi/2 the axis comes from the antisymmetric part ``v = sin(th) k``; above, from the
    symmetric part ``(R + R^T)/2 - cos(th) I = (1 - cos(th)) k k^T`` (its largest column), with the sign
    taken from ``v``. At exactly pi both signs are the same rotation.

    Args:
        R: (*, 3, 3) rotation matrices.

    Returns:
        (*, 3) axis * angle, angle in [0, pi].
    """
    _check_last("matrix_to_rodrigues: R", R, (3, 3))
    v = 0.5 * torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], dim=-1
    )
    c = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1, 1)
    s2 = (v * v).sum(-1)
    near_zero = c > 0  # angle < pi/2: the antisymmetric part is well conditioned

    # Branch 1: r = v * th / sin(th), with th / sin(th) = asin(s)/s by its series for tiny s.
    tiny = s2 < 1e-6
    s2s = torch.where(tiny | ~near_zero, torch.ones_like(s2), s2)
    s = s2s.sqrt()
    f_big = torch.atan2(s, c.where(near_zero, torch.ones_like(c))) / s
    f_small = 1 + s2 / 6 + 3 * s2 * s2 / 40
    r1 = v * torch.where(tiny, f_small, f_big)[..., None]

    # Branch 2: axis from the symmetric part.
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    M = 0.5 * (R + R.transpose(-1, -2)) - c[..., None, None] * eye
    j = torch.diagonal(M, dim1=-2, dim2=-1).argmax(-1)
    col = torch.gather(M, -1, j[..., None, None].expand(M.shape[:-1] + (1,)))[..., 0]
    n2 = (col * col).sum(-1)
    n2s = torch.where(near_zero | (n2 <= 0), torch.ones_like(n2), n2)
    k = col * n2s.rsqrt()[..., None]
    sv = (k * v).sum(-1)
    sign = torch.where(sv < 0, -torch.ones_like(sv), torch.ones_like(sv))
    k = k * sign[..., None]
    th = torch.atan2(sv * sign, c)
    r2 = k * th[..., None]
    return torch.where(near_zero[..., None], r1, r2)


# ----------------------------------------------------------------------------------------------------------
# Triangulation
# ----------------------------------------------------------------------------------------------------------
