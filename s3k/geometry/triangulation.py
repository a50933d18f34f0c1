"""Weighted triangulation: the point nearest to a set of rays, batched (docs/method.md#triangulation).

The closed-form 3x3 solve of the weighted normal equations, guarded against degenerate systems, in three
layouts chosen by batch size (small batches, planar de-interleaved buffers for large ones, and an optional
torch.compile'd kernel), and its pixel front end :func:`triangulate_pixels`.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from s3k.geometry.cameras import Cameras
from s3k.geometry.projection import pixel_rays
from s3k.geometry.shapes import broadcast_shapes, check_last


def triangulate_rays(
    origins: Tensor,
    directions: Tensor,
    weights: Tensor | None = None,
    *,
    min_weight: float = 1e-6,
    min_rel_det: float = 1e-5,
    fused: bool = False,
) -> tuple[Tensor, Tensor]:
    """Weighted least-squares intersection of rays (paper eq. 2 with the weight in both sums).

    The maths and the correction to the paper: docs/method.md#triangulation.

    ``x = (sum_v w_v (I - d_v d_v^T))^-1  sum_v w_v (I - d_v d_v^T) a_v`` minimizes the weighted sum of
    squared distances to the rays. The 3x3 system is solved in closed form (adjugate / determinant), batched.

    With ``A = sum_v w_v (I - d_v d_v^T)`` the system is declared degenerate (``valid=False``, ``X = 0``, zero
    gradient) when the total weight ``sum_v w_v <= min_weight``, or when ``det(A) <= min_rel_det *
    (trace(A)/3)^3``: a scale-invariant test that catches a single effective view (A has rank 2) and
    near-parallel rays (two rays at angle alpha give det/(trace/3)^3 = 27/32 sin^2 alpha, so the default
    1e-5 rejects pairs closer than about 0.2 degrees). Scaling all weights changes neither X nor the test
    (apart from ``min_weight``).

    Args:
        origins: (*, V, 3) ray origins.
        directions: (*, V, 3) non-zero ray directions (normalized here; `pixel_rays` returns unit vectors).
        weights: (*, V) non-negative weights (cast to the rays' dtype), or None for unit weights. All leading
            dims broadcast.
        min_weight: smallest valid total weight.
        min_rel_det: smallest valid ``det(A) / (trace(A)/3)^3``.
        fused: run the same solve as one ``torch.compile``'d loop over the points (reads each input once
            instead of a few dozen vectorized passes; several times faster on large batches). The first call
            in a process compiles (10-60 s on 2 cores; cached on disk by torch), so use it for large or
            repeated batches, e.g. offline tracking; needs a C++ compiler on CPU.

    Returns:
        X: (*, 3) points (zeros where invalid).
        valid: (*) bool.

    Example:
        >>> o = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
        >>> d = torch.nn.functional.normalize(torch.tensor([[1.0, 1, 0], [-1.0, 1, 0]]), dim=-1)
        >>> triangulate_rays(o, d)
        (tensor([0.5000, 0.5000, 0.0000]), tensor(True))
    """
    check_last("triangulate_rays: origins", origins, (3,), min_ndim=2)
    check_last("triangulate_rays: directions", directions, (3,), min_ndim=2)
    if weights is None:
        weights = directions.new_ones(()).expand(directions.shape[:-1])
    elif not isinstance(weights, Tensor) or weights.ndim < 1 or not weights.is_floating_point():
        raise ValueError(
            f"triangulate_rays: weights: expected a floating tensor of shape (*, V), got "
            f"{getattr(weights, 'shape', type(weights).__name__)}"
        )
    if origins.dtype != directions.dtype:
        raise ValueError(
            f"triangulate_rays: origins ({origins.dtype}) and directions ({directions.dtype}) differ in dtype"
        )
    weights = weights.to(origins.dtype)
    names = ["triangulate_rays: origins", "triangulate_rays: directions", "triangulate_rays: weights"]
    lead = broadcast_shapes(names, [origins.shape[:-1], directions.shape[:-1], weights.shape])
    if lead[-1] == 0:
        raise ValueError("triangulate_rays: no views (V = 0)")
    if fused:
        return _triangulate_fused(origins, directions, weights, min_weight, min_rel_det)
    return _triangulate(origins, directions, weights, min_weight, min_rel_det)


# Above this many points a batch is solved in chunks that stay in the CPU's L2/L3 cache; every step of the
# solve is a separate elementwise pass, so keeping its operands cached is what makes large batches fast.
_TRIANGULATE_CHUNK = 131072
# Below this many points the planar layout does not pay for its copies.
_PLANAR_MIN = 2048
SMALL_BATCH = _PLANAR_MIN
"""Batches of fewer points than this are solved in matrix form (:func:`solve_projected`)."""


def _planar(x: Tensor, select: Tensor | None = None, out: Tensor | None = None) -> Tensor:
    """(N, V, c) -> (c, V, N) contiguous, so that every later op runs on contiguous, vectorizable rows.

    A product with a permutation matrix is a de-interleaving copy that the BLAS does several times faster than
    ``permute(...).contiguous()`` (which for c = 3 or 1 is a strided gather); it is exact as long as float32
    matmuls are not allowed to drop precision.
    """
    n, v, c = x.shape
    if n < 4096 or (x.dtype == torch.float32 and torch.get_float32_matmul_precision() != "highest"):
        return x.permute(2, 1, 0).contiguous()
    if select is None:
        select = _planar_select(v, c, x.dtype, x.device)
    if out is not None:  # a reused buffer: no fresh pages to fault in for every chunk
        return torch.mm(select, x.reshape(n, c * v).T, out=out[: c * v * n].view(c * v, n)).view(c, v, n)
    return torch.mm(select, x.reshape(n, c * v).T).view(c, v, n)


def _planar_select(v: int, c: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The permutation matrix of `_planar`: row ``k * v + j`` picks input column ``j * c + k``."""
    order = torch.arange(c * v, device=device).view(v, c).T.reshape(-1)
    return torch.eye(c * v, dtype=dtype, device=device)[order]


def _solve_planar(
    O: Tensor, D: Tensor, Wv: Tensor, min_weight: float, min_rel_det: float
) -> tuple[Tensor, Tensor]:
    """The weighted normal equations for O, D (3, V, N) and Wv (V, N); returns X (N, 3), valid (N,)."""
    # A = W I - S with S = sum_v w d^ d^T (d^ the unit direction; the off-diagonal entries of S enter A with
    # a minus sign, folded into the cofactors below) and b = sum_v w (a - d^ (d^ . a)). With d^ = d / |d|
    # both need only w / |d|^2, so directions are normalized for the price of one division per view; that
    # keeps I - d^ d^T an exact projector for float32 rays, unit only to ~1e-7, an error the solve amplifies.
    # Accumulating view by view into (3, N) sums touches each input once and makes no (3, V, N) temporaries.
    tiny = torch.finfo(O.dtype).tiny
    for v in range(Wv.shape[0]):
        d, o, w = D[:, v], O[:, v], Wv[v]
        dd = (d[0] * d[0]).addcmul_(d[1], d[1]).addcmul_(d[2], d[2])
        wd = d * (w / dd.clamp(min=tiny))
        da = (d[0] * o[0]).addcmul_(d[1], o[1]).addcmul_(d[2], o[2])
        if v == 0:  # the first view initializes the sums (no zero-filled buffers)
            s_diag = wd * d  # sxx, syy, szz
            s_xy_yz = wd[:2] * d[1:]
            sxz = wd[0] * d[2]
            b = torch.addcmul(o * w, wd, da, value=-1)
        else:
            s_diag.addcmul_(wd, d)
            s_xy_yz.addcmul_(wd[:2], d[1:])
            sxz.addcmul_(wd[0], d[2])
            b.addcmul_(o, w).addcmul_(wd, da, value=-1)
    sxy, syz = s_xy_yz.unbind(0)
    W = Wv.sum(0)
    axx, ayy, azz = (W - s_diag).unbind(0)
    bx, by, bz = b.unbind(0)
    # Cofactors of the symmetric A (its adjugate), with a_xy = -sxy etc.
    cxx = torch.addcmul(ayy * azz, syz, syz, value=-1)
    cyy = torch.addcmul(axx * azz, sxz, sxz, value=-1)
    czz = torch.addcmul(axx * ayy, sxy, sxy, value=-1)
    cxy = torch.addcmul(sxz * syz, sxy, azz)
    cxz = torch.addcmul(sxy * syz, sxz, ayy)
    cyz = torch.addcmul(sxy * sxz, axx, syz)
    det = torch.addcmul(torch.addcmul(axx * cxx, sxy, cxy, value=-1), sxz, cxz, value=-1)
    tr3 = (axx + ayy + azz) * (1 / 3)
    # For a PSD A, det/(trace/3)^3 in [0, 1] measures how far A is from singular independently of the weights'
    # scale; written as a product so that zero weights give False rather than 0/0.
    valid = (W > min_weight) & (det > min_rel_det * tr3 * tr3 * tr3)
    inv_det = torch.where(valid, 1 / torch.where(valid, det, torch.ones_like(det)), torch.zeros_like(det))
    X = torch.stack(
        [
            torch.addcmul(torch.addcmul(cxx * bx, cxy, by), cxz, bz),
            torch.addcmul(torch.addcmul(cxy * bx, cyy, by), cyz, bz),
            torch.addcmul(torch.addcmul(cxz * bx, cyz, by), czz, bz),
        ],
        dim=-1,
    )
    return X * inv_det[:, None], valid


def _triangulate(
    o: Tensor, d: Tensor, w: Tensor, min_weight: float, min_rel_det: float
) -> tuple[Tensor, Tensor]:
    lead = broadcast_shapes(["origins", "directions", "weights"], [o.shape[:-2], d.shape[:-2], w.shape[:-1]])
    n = math.prod(lead)
    if n < _PLANAR_MIN:
        # Few points (a training batch): the cost is per op, and the matrix form has the fewest ops.
        return _solve_small(o, d, w, min_weight, min_rel_det)
    v = max(o.shape[-2], d.shape[-2], w.shape[-1])
    o = o.expand(lead + (v, 3)).reshape(n, v, 3)
    d = d.expand(lead + (v, 3)).reshape(n, v, 3)
    w = w.expand(lead + (v,)).reshape(n, v, 1)
    grad = torch.is_grad_enabled() and (o.requires_grad or d.requires_grad or w.requires_grad)
    if grad or n <= _TRIANGULATE_CHUNK:
        X, valid = _solve_planar(_planar(o), _planar(d), _planar(w)[0], min_weight, min_rel_det)
    else:
        X = o.new_empty(n, 3)
        valid = torch.empty(n, dtype=torch.bool, device=o.device)
        sel3 = _planar_select(v, 3, o.dtype, o.device)
        sel1 = _planar_select(v, 1, o.dtype, o.device)
        buf_o, buf_d, buf_w = (o.new_empty(c * v * _TRIANGULATE_CHUNK) for c in (3, 3, 1))
        for i in range(0, n, _TRIANGULATE_CHUNK):
            j = min(i + _TRIANGULATE_CHUNK, n)
            O, D = _planar(o[i:j], sel3, buf_o), _planar(d[i:j], sel3, buf_d)
            Wv = _planar(w[i:j], sel1, buf_w)[0]
            X[i:j], valid[i:j] = _solve_planar(O, D, Wv, min_weight, min_rel_det)
    return X.reshape(lead + (3,)), valid.reshape(lead)


def _solve_small(
    o: Tensor, d: Tensor, w: Tensor, min_weight: float, min_rel_det: float
) -> tuple[Tensor, Tensor]:
    """The same solve as `_solve_planar` in matrix form on (*, V, 3), (*, V, 3), (*, V) inputs.

    Few points cost per op, not per byte: this form needs about a third of the ops of the others.
    """
    return solve_projected(o, ray_projectors(d), w, min_weight, min_rel_det)


def ray_projectors(d: Tensor) -> Tensor:
    """``I - d^ d^T`` (*, V, 3, 3) of directions (*, V, 3) (``d^ = d / |d|``): the part of the small-batch
    solve that does not depend on the weights, for solving the same rays under several weightings
    (:func:`solve_projected`)."""
    d = d * (d * d).sum(-1, keepdim=True).clamp(min=torch.finfo(d.dtype).tiny).rsqrt()
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    return eye - d[..., :, None] * d[..., None, :]


def solve_projected(
    o: Tensor, P: Tensor, w: Tensor, min_weight: float = 1e-6, min_rel_det: float = 1e-5
) -> tuple[Tensor, Tensor]:
    """`triangulate_rays` of origins (*, V, 3), projectors (*, V, 3, 3) (:func:`ray_projectors`) and weights
    (*, V), for few points (the same arithmetic as its small-batch form): ``(X (*, 3), valid (*))``."""
    wP = w[..., None, None] * P  # (*, V, 3, 3)
    A = wP.sum(-3)
    b = (wP @ o[..., None]).sum(-3)  # (*, 3, 1)
    r0, r1, r2 = A.unbind(-2)
    # Rows of the adjugate are cross products of the rows of A (A is symmetric, so is its adjugate).
    cross = torch.linalg.cross
    adj = torch.stack([cross(r1, r2), cross(r2, r0), cross(r0, r1)], -2)
    det = (r0 * adj[..., 0, :]).sum(-1)
    tr3 = A.diagonal(dim1=-2, dim2=-1).sum(-1) * (1 / 3)
    valid = (w.sum(-1) > min_weight) & (det > min_rel_det * tr3 * tr3 * tr3)
    inv_det = torch.where(valid, 1 / torch.where(valid, det, torch.ones_like(det)), torch.zeros_like(det))
    return (adj @ b)[..., 0] * inv_det[..., None], valid


def _solve_interleaved(
    o: Tensor, d: Tensor, w: Tensor, min_weight: float, min_rel_det: float
) -> tuple[Tensor, Tensor]:
    """`_solve_planar` on (N, V, 3), (N, V, 3), (N, V) inputs, for torch.compile to fuse into one loop."""
    wn = w / (d * d).sum(-1).clamp(min=torch.finfo(d.dtype).tiny)  # w / |d|^2 normalizes d (see there)
    dx, dy, dz = d.unbind(-1)
    wdx, wdy, wdz = wn * dx, wn * dy, wn * dz
    W = w.sum(-1)
    axx = W - (wdx * dx).sum(-1)
    ayy = W - (wdy * dy).sum(-1)
    azz = W - (wdz * dz).sum(-1)
    sxy = (wdx * dy).sum(-1)
    syz = (wdy * dz).sum(-1)
    sxz = (wdx * dz).sum(-1)
    da = (d * o).sum(-1, keepdim=True)
    wd = torch.stack([wdx, wdy, wdz], -1)
    bx, by, bz = (w[..., None] * o - wd * da).sum(-2).unbind(-1)
    cxx = ayy * azz - syz * syz
    cyy = axx * azz - sxz * sxz
    czz = axx * ayy - sxy * sxy
    cxy = sxz * syz + sxy * azz
    cxz = sxy * syz + sxz * ayy
    cyz = sxy * sxz + axx * syz
    det = axx * cxx - sxy * cxy - sxz * cxz
    tr3 = (axx + ayy + azz) * (1 / 3)
    valid = (W > min_weight) & (det > min_rel_det * tr3 * tr3 * tr3)
    inv_det = torch.where(valid, 1 / torch.where(valid, det, torch.ones_like(det)), torch.zeros_like(det))
    X = torch.stack(
        [cxx * bx + cxy * by + cxz * bz, cxy * bx + cyy * by + cyz * bz, cxz * bx + cyz * by + czz * bz], -1
    )
    return X * inv_det[..., None], valid


_FUSED_SOLVE: Any = None


def _triangulate_fused(
    o: Tensor, d: Tensor, w: Tensor, min_weight: float, min_rel_det: float
) -> tuple[Tensor, Tensor]:
    global _FUSED_SOLVE
    if _FUSED_SOLVE is None:
        # Static shapes except the number of points (marked dynamic below): a fixed V lets the compiler unroll
        # the loop over views, which doubles the speed against a fully dynamic kernel.
        _FUSED_SOLVE = torch.compile(_solve_interleaved, dynamic=False)
    lead = broadcast_shapes(["origins", "directions", "weights"], [o.shape[:-2], d.shape[:-2], w.shape[:-1]])
    v = max(o.shape[-2], d.shape[-2], w.shape[-1])
    n = math.prod(lead)
    o = o.expand(lead + (v, 3)).reshape(n, v, 3)
    d = d.expand(lead + (v, 3)).reshape(n, v, 3)
    w = w.expand(lead + (v,)).reshape(n, v)
    if n >= 2:  # sizes 0 and 1 are always specialized by the compiler
        for x in (o, d, w):
            torch._dynamo.mark_dynamic(x, 0)
    X, valid = _FUSED_SOLVE(o, d, w, float(min_weight), float(min_rel_det))
    return X.reshape(lead + (3,)), valid.reshape(lead)


def triangulate_pixels(
    cams: Cameras,
    uv: Tensor,
    weights: Tensor | None = None,
    iters: int = 5,
    **kwargs: Any,
) -> tuple[Tensor, Tensor]:
    """Triangulate (distorted) pixel detections seen by several cameras.

    The view axis is the last leading camera dim: cameras ``(B, C)`` with uv ``(B, C, K, 2)`` give X
    ``(B, K, 3)``.

    Args:
        cams: cameras with leading dims L = (*L', V), V >= 1.
        uv: (*L, N, 2) pixels; leading dims broadcast against L.
        weights: (*L, N) per-view weights (broadcastable), or None for unit weights. Zero drops a view.
        iters: Newton iterations of `undistort`.
        **kwargs: ``min_weight``, ``min_rel_det``, ``fused`` of `triangulate_rays`.

    Returns:
        X: (*L', N, 3) world points (zeros where invalid).
        valid: (*L', N) bool.
    """
    if len(cams.shape) < 1:
        raise ValueError("triangulate_pixels: cameras need a view dim (the last leading dim)")
    check_last("triangulate_pixels: uv", uv, (2,), min_ndim=3)
    if uv.dtype != cams.dtype:
        raise ValueError(f"triangulate_pixels: uv dtype {uv.dtype} differs from the cameras' {cams.dtype}")
    lead = broadcast_shapes(["triangulate_pixels: uv", "cameras"], [uv.shape[:-2], cams.shape])
    n = uv.shape[-2]
    if weights is None:
        weights = torch.ones((), dtype=uv.dtype, device=uv.device)
    if not isinstance(weights, Tensor) or not weights.is_floating_point():
        raise ValueError(
            f"triangulate_pixels: weights: expected a floating tensor, got {type(weights).__name__}"
        )
    try:
        weights = weights.expand(lead + (n,))
    except RuntimeError:
        raise ValueError(
            f"triangulate_pixels: weights {tuple(weights.shape)} do not broadcast to {tuple(lead) + (n,)}"
        ) from None
    o, d = pixel_rays(cams, uv, iters=iters)
    X, valid = triangulate_rays(o.transpose(-2, -3), d.transpose(-2, -3), weights.transpose(-1, -2), **kwargs)
    return X, valid


def workspace_centre(cams: Cameras) -> tuple[Tensor, Tensor]:
    """Where a rig's cameras look: the point nearest to their optical axes (the rays through each principal
    point), triangulated with unit weights.

    Args:
        cams: cameras ``(*L, C)``.

    Returns:
        ``(centre (*L, 3), valid (*L))``: invalid where the axes do not meet (fewer than two cameras,
        parallel axes).
    """
    principal = cams.K[..., :2, 2][..., None, :]  # (*L, C, 1, 2)
    centre, valid = triangulate_pixels(cams, principal)  # (*L, 1, 3)
    return centre[..., 0, :], valid[..., 0]


def triangulate_labels(cams: Cameras, uv: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """The one triangulation of 2D labels: every labelled view with unit weight, a keypoint valid where at
    least two views label it and the rays are not degenerate (the supervised loss's target, the crop rule,
    the labelled layout, which labels are usable, the labelling app).

    Args:
        cams: cameras ``(*L, C)``.
        uv: ``(*L, C, K, 2)`` labels in the cameras' pixels (anything where not labelled, NaN included).
        mask: ``(*L, C, K)`` bool, the labelled views.

    Returns:
        ``(X (*L, K, 3), valid (*L, K))`` in the cameras' dtype; X is 0 where invalid.
    """
    uv = torch.as_tensor(uv).to(device=cams.K.device, dtype=cams.dtype)
    labelled = torch.as_tensor(mask).to(device=cams.K.device, dtype=torch.bool) & torch.isfinite(uv).all(-1)
    # an unlabelled view gets a harmless pixel and no weight: it must not reach the solver as NaN
    uv = torch.where(labelled[..., None], uv, torch.zeros_like(uv))
    X, valid = triangulate_pixels(cams, uv, labelled.to(cams.dtype))
    return X, valid & (labelled.sum(dim=-2) >= 2)
