"""Cameras: the OpenCV pinhole + distortion model as one batched :class:`Cameras` (projection and rays:
:mod:`s3k.geometry.projection`; distortion: :mod:`s3k.geometry.distortion`; rotations:
:mod:`s3k.geometry.rotations`).

Everything here is pure torch, broadcasts over leading dimensions, works in float32 and float64 and is
differentiable. Conventions (docs/architecture.md): ``x_cam = R @ x_world + t``; pixel (0, 0) is the centre
of the top-left pixel, u right, v down; ``K`` is a general 3x3 (skew allowed, so warps ``K <- M @ K`` stay
exact); ``dist = (k1, k2, p1, p2, k3)`` as in OpenCV.

Dimension names: ``L`` the leading dims of a camera set (e.g. ``(C,)`` for a rig, ``(B, C)`` per frame),
``N`` points, ``V`` views of one point.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch
from torch import Tensor

from s3k.geometry.rotations import rodrigues_to_matrix
from s3k.geometry.shapes import broadcast_shapes, check_last


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
        check_last("Cameras.K", self.K, (3, 3))
        check_last("Cameras.R", self.R, (3, 3))
        check_last("Cameras.t", self.t, (3,))
        if self.dist is None:
            self.dist = self.K.new_zeros(self.K.shape[:-2] + (5,))
        check_last("Cameras.dist", self.dist, (5,))
        fields = {"K": self.K, "dist": self.dist, "R": self.R, "t": self.t}
        for name, x in fields.items():
            if x.dtype != self.K.dtype or x.device != self.K.device:
                raise ValueError(
                    f"Cameras.{name}: dtype/device {x.dtype}/{x.device} differs from "
                    f"Cameras.K {self.K.dtype}/{self.K.device}"
                )
        lead = broadcast_shapes(
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
