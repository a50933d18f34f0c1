"""Argument checks shared by the geometry modules: a tensor's trailing shape and the broadcast of leading
dimensions, with errors that name the argument."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def check_last(name: str, x: Tensor, sizes: Sequence[int], min_ndim: int | None = None) -> None:
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


def broadcast_shapes(names: Sequence[str], shapes: Sequence[Sequence[int]]) -> torch.Size:
    """Broadcast leading shapes, with an error that names the arguments."""
    out = _broadcast_shape(*shapes)
    if out is None:
        desc = ", ".join(f"{n} {tuple(s)}" for n, s in zip(names, shapes))
        raise ValueError(f"leading dimensions do not broadcast: {desc}")
    return out
