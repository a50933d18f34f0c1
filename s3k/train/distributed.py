"""Data-parallel training helpers: joining torchrun's process group, sharding frames, agreeing across ranks.

Under ``torchrun --nproc-per-node N`` every rank runs the same loop on its own shard of the frames, wrapped in
DistributedDataParallel (gloo on CPU, NCCL on GPU); only rank 0 writes logs and checkpoints. Without torchrun
(``WORLD_SIZE`` unset or 1) every helper is a no-op.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn


@dataclass
class DistInfo:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    created: bool = False

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str) -> DistInfo:
    """Join the process group when launched by torchrun (WORLD_SIZE > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    created = False
    if not dist.is_initialized():
        use_nccl = torch.cuda.is_available() and device != "cpu"
        dist.init_process_group("nccl" if use_nccl else "gloo")
        created = True
    return DistInfo(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")), created)


def finish_distributed(info: DistInfo) -> None:
    """Leave the process group if :func:`init_distributed` created it."""
    if info.created and dist.is_initialized():
        dist.destroy_process_group()


def shard(ids: np.ndarray, info: DistInfo) -> np.ndarray:
    """Rank's share of the frames (every rank keeps all frames when there are fewer than ranks)."""
    if not info.enabled or len(ids) < info.world:
        return ids
    return ids[info.rank::info.world]


def wrap_model(net: nn.Module, device: torch.device, info: DistInfo) -> nn.Module:
    """``net`` in DistributedDataParallel when several ranks train, else ``net`` itself."""
    if not info.enabled:
        return net
    # 1x1 kernels have ambiguous channels-last strides; DDP then copies their (tiny) gradients and warns.
    warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
    ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(net, device_ids=ids)


def gather(obj: Any, info: DistInfo) -> list[Any]:
    """Every rank's ``obj``, in rank order (a one-element list without DDP)."""
    if not info.enabled:
        return [obj]
    out: list[Any] = [None] * info.world
    dist.all_gather_object(out, obj)
    return out


def all_ranks(flag: bool, device: torch.device, info: DistInfo) -> bool:
    """True when ``flag`` is True on every rank (so that all ranks take or skip a step together)."""
    ok = torch.tensor([float(flag)], device=device)
    if info.enabled:
        dist.all_reduce(ok, op=dist.ReduceOp.MIN)
    return bool(ok.item())


def broadcast_buffers(net: nn.Module, info: DistInfo) -> None:
    """Give every rank rank 0's buffers (normalization statistics).

    DDP keeps parameters identical, but buffers are only broadcast at each forward, so after the last step the
    ranks' statistics differ from those rank 0 checkpointed.
    """
    if info.enabled:
        for buf in net.buffers():
            dist.broadcast(buf.data, 0)
