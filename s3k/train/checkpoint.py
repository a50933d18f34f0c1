"""The training checkpoint ``RUN/checkpoint.pt``: its one writer (:func:`save_checkpoint`) and one reader
(:func:`load_checkpoint`).

A checkpoint is a dict of tensors and plain values only, so that it loads with ``weights_only=True`` and
loading never runs code from the file::

    format         "s3k-checkpoint/1"
    step           completed optimizer steps
    model          the network's state dict
    optimizer      Adam's state dict
    scheduler      the learning-rate schedule's state dict
    rng            one dict per rank: {"gen": batch/augmentation generator state, "torch": global state,
                   "cuda": [per-device states] when CUDA is available}; the ranks share one stream, so a
                   resume, with any number of ranks, continues the first
    nonfinite_run  consecutive non-finite steps before this one
    meta           ``DetectorMeta.to_dict()``
    config         ``TrainConfig.to_dict()`` (flat)
    teacher        the teacher network's state dict (``--teacher-ema``; absent without one)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from s3k.detector import atomic_save, load_torch_file

CHECKPOINT_FORMAT = "s3k-checkpoint/1"
_KEYS = ("step", "model", "optimizer", "scheduler", "rng")


def rng_state(gen: torch.Generator) -> dict[str, Any]:
    """This process's random states: ``gen`` (batches, augmentation), torch's global and CUDA's."""
    state: dict[str, Any] = {"gen": gen.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(gen: torch.Generator, state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned."""
    gen.set_state(state["gen"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | Path, *, step: int, model: dict[str, Any], optimizer: dict[str, Any],
                    scheduler: dict[str, Any], rng: list[dict[str, Any]], nonfinite_run: int,
                    meta: dict[str, Any], config: dict[str, Any], teacher: dict[str, Any] | None = None
                    ) -> None:
    """Write the checkpoint atomically (a kill leaves the previous one in place)."""
    state = {"format": CHECKPOINT_FORMAT, "step": step, "model": model, "optimizer": optimizer,
             "scheduler": scheduler, "rng": rng, "nonfinite_run": nonfinite_run, "meta": meta,
             "config": config}
    if teacher is not None:
        state["teacher"] = teacher
    atomic_save(state, path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        UserError: naming the file when it is not an s3k checkpoint (foreign, crafted, truncated or older).
    """
    return load_torch_file(path, "checkpoint", _KEYS)


def read_checkpoint_step(path: str | Path) -> int:
    """The completed steps recorded in the checkpoint ``path`` (``UserError`` when it is not one)."""
    return int(load_checkpoint(path)["step"])
