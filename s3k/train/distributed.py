"""Data-parallel training helpers: joining torchrun's process group, each rank's part of a batch, agreeing
across ranks.

Under ``torchrun --nproc-per-node N`` every rank runs the loop one process runs, wrapped in
DistributedDataParallel (gloo on CPU, NCCL on GPU), so that N ranks train what one process trains: the batch
sizes are global; every rank holds every frame, draws and augments the whole batch from the same random
stream as one process (``seed * 1000``), then passes only its own contiguous ``batch / N`` frames
(:func:`part`) forward and backward. Every loss is a sum over frames divided by the frames of the batch, so
the mean of the ranks' losses, and DDP's mean of their gradients, are those of the whole batch;
:func:`mean_terms` gives every rank the whole batch's logged terms. Only rank 0 writes logs and checkpoints.
Without torchrun (``WORLD_SIZE`` unset or 1) every helper is a no-op.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

from s3k.base.choices import Device
from s3k.base.errors import UserError


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


def init_distributed(device: Device) -> DistInfo:
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


def world_size() -> int:
    """The number of processes torchrun started (1 without torchrun)."""
    return max(int(os.environ.get("WORLD_SIZE", "1")), 1)


def check_batches(batch_labelled: int, batch_unlabelled: int, unsup: bool, world: int) -> None:
    """Refuse batch sizes that ``world`` ranks cannot split into equal parts.

    Raises:
        UserError: naming the batch size and the option that fixes it.
    """
    sizes = [("--batch-labelled", batch_labelled)]
    if unsup:
        sizes.append(("--batch-unlabelled", batch_unlabelled))
    for option, n in sizes:
        if n % world:
            raise UserError(f"{option} {n} does not split over the {world} processes torchrun started (each "
                            "takes an equal part of the global batch)",
                            hint=f"give {option} a multiple of {world}")


def part(batch: tuple[Any, ...], info: DistInfo) -> tuple[Any, ...]:
    """This rank's contiguous ``1 / world`` of every field of ``batch`` (frames along the first dimension;
    :class:`s3k.geometry.Cameras` and None fields too); ``batch`` itself without DDP."""
    if not info.enabled:
        return batch
    n = len(batch[0]) // info.world
    return tuple(None if x is None else x[info.rank * n:(info.rank + 1) * n] for x in batch)


def mean_terms(terms: dict[str, float], device: torch.device, info: DistInfo) -> dict[str, float]:
    """The mean over the ranks of each of ``terms`` (the same keys on every rank): for terms that are sums
    over frames divided by the frames of a rank's equal part, or means over them, the whole batch's value."""
    if not info.enabled:
        return terms
    keys = sorted(terms)
    values = torch.tensor([terms[k] for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(values)
    means = dict(zip(keys, (values / info.world).tolist()))
    return {k: means[k] for k in terms}


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
