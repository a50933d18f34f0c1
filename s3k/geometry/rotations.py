"""Rotations: Rodrigues vectors to matrices and back, batched and differentiable (pure torch)."""

from __future__ import annotations

import torch
from torch import Tensor

from s3k.geometry.shapes import check_last


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
    check_last("rodrigues_to_matrix: rvec", rvec, (3,))
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
    check_last("matrix_to_rodrigues: R", R, (3, 3))
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
