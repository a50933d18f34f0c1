"""The detector's network on the CPU as a frozen TorchScript graph: the same convolutions with the same
weights, without Python's per-module cost.

A :class:`s3k.model.UNet` runs some sixty modules per call; on the CPU at batch 1 (four views of one frame)
their Python dispatch is a large share of a two-pass frame. :class:`FrozenNetwork` traces the network once per
input shape (the batch of views times the pass's fixed input size) and freezes it
(:func:`torch.jit.freeze`: weights become constants, no module attributes are looked up per call). Its
outputs equal the eager network's to float rounding (the same ATen operators in the same order, the weights
folded as constants: a few units in the last place of float32); every call of one input shape, the first
included, goes through the same graph, so the same input gives the same output bit for bit.
tests/detector/test_frozen_network.py and ``benchmarks/inference.py --check`` compare them.

It is used where it is exact and cheap: s3k's own :class:`s3k.model.UNet` on the CPU, float32 (no autocast),
without gradients; each new graph is checked once against the eager network on the input that made it.
Anything else, a network that cannot be traced or a graph that disagrees, runs the eager module unchanged; so
does a detector made with ``fast=False`` (the plain path, for comparison).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch
from torch import Tensor, nn

from s3k.model import UNet

__all__ = ["FrozenNetwork"]

MAX_SHAPES = 4
"""Input shapes kept traced at once (batch sizes of a run: full batches and the last, shorter one)."""


class FrozenNetwork:
    """Callable like ``net``: images ``(N, 3, h, w)`` -> logits, through a frozen trace of ``net`` per input
    shape where that is exact (module docstring), else through ``net`` itself.

    Attributes:
        net: the eager network (in eval mode; the detector's fused U-Net).
        frozen: ``{(shape, memory format): traced module}`` of the shapes seen so far.
        eager: every call runs the network eagerly (not ``enabled``, not on the CPU, or it could not be
            traced).
    """

    def __init__(self, net: Callable[[Tensor], Tensor], device: torch.device, enabled: bool = True) -> None:
        self.net, self.device = net, device
        self.frozen: dict[tuple, torch.jit.ScriptModule] = {}
        self.eager = not (enabled and isinstance(net, UNet) and device.type == "cpu")

    def __call__(self, x: Tensor) -> Tensor:
        if (self.eager or torch.is_grad_enabled() or torch.is_autocast_enabled("cpu")
                or x.device.type != "cpu" or x.dtype != torch.float32):
            return self.net(x)
        key = (tuple(x.shape), x.is_contiguous(memory_format=torch.channels_last))
        module = self.frozen.get(key)
        if module is None:  # a new shape: a graph checked against the eager answer, then its own answer
            out = self.net(x)
            module = self._trace(x, key, out)
            if module is None:
                return out
        return module(x)

    def _trace(self, x: Tensor, key: tuple, out: Tensor) -> torch.jit.ScriptModule | None:
        """Keep and return the frozen trace of ``net`` on inputs like ``x`` if it gives ``out`` (the eager
        network's logits of ``x``); else, or if tracing fails, run eagerly from then on (None)."""
        assert isinstance(self.net, nn.Module)
        if len(self.frozen) >= MAX_SHAPES:
            self.frozen.pop(next(iter(self.frozen)))
        # traced outside inference mode on an ordinary tensor of the same shape and layout
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # TracerWarning on shape checks; torch.jit's deprecation notes
            example = torch.zeros(x.shape, dtype=x.dtype)
            if key[1]:
                example = example.contiguous(memory_format=torch.channels_last)
            try:
                module = torch.jit.freeze(torch.jit.trace(self.net.eval(), (example,), check_trace=False))
                same = torch.allclose(module(x), out, rtol=1e-4, atol=1e-4)
            except Exception:  # noqa: BLE001 - any network torch.jit cannot trace runs eagerly, as before
                same = False
        if same:
            self.frozen[key] = module
            return module
        self.eager = True
        return None
