"""An insertion agent's checkpoint ``OUT/checkpoint/``: the policy's and optimizers' state dicts
(``agent.pt``), the filled part of the replay buffer (``replay.npz``) and ``state.json`` (environment steps,
gradient updates, episodes), written as one unit so that a killed run resumes from its last complete
checkpoint (:mod:`s3k.robot.agents`). Nothing is read with ``pickle``: state dicts through
``torch.load(weights_only=True)`` and the buffer through ``numpy.load(allow_pickle=False)``.
"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_bytes, atomic_write_json
from s3k.detector import atomic_save, load_torch_file

__all__ = ["BUFFER_FIELDS", "checkpoint_folder", "load_checkpoint", "save_checkpoint"]

BUFFER_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def save_checkpoint(model, folder: Path, state: dict) -> None:
    """Writes the agent, its replay buffer and ``state.json`` into ``folder`` as one unit.

    They are written into ``folder.tmp`` first, which then takes the place of ``folder`` by two renames (the
    previous checkpoint is kept as ``folder.old`` in between), so a kill at any point leaves one complete
    checkpoint: :func:`checkpoint_folder` finds it.
    """

    tmp, old = folder.with_name(folder.name + ".tmp"), folder.with_name(folder.name + ".old")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    atomic_save({"policy": model.policy.state_dict(), "actor_optimizer": model.actor.optimizer.state_dict(),
                 "critic_optimizer": model.critic.optimizer.state_dict()}, tmp / "agent.pt")
    rb = model.replay_buffer
    n = rb.buffer_size if rb.full else rb.pos
    buf = io.BytesIO()
    arrays = {f: getattr(rb, f)[:n] for f in BUFFER_FIELDS}
    if getattr(model, "expert_actions", None) is not None:
        arrays["expert_actions"] = model.expert_actions[:n]
    np.savez(buf, **arrays, pos=np.array(rb.pos), full=np.array(rb.full))
    atomic_write_bytes(buf.getvalue(), tmp / "replay.npz")
    atomic_write_json(state, tmp / "state.json")
    if folder.exists():
        shutil.rmtree(old, ignore_errors=True)
        folder.rename(old)
    tmp.rename(folder)
    shutil.rmtree(old, ignore_errors=True)


def checkpoint_folder(folder: Path) -> Path | None:
    """The complete checkpoint to resume from: ``folder``, or ``folder.old`` when a kill came between the
    two renames of :func:`save_checkpoint`; None when there is none."""
    for candidate in (folder, folder.with_name(folder.name + ".old")):
        if (candidate / "state.json").is_file():
            return candidate
    return None


def load_checkpoint(model, folder: Path) -> dict:
    """Restores what :func:`save_checkpoint` wrote into ``model``; returns ``state.json``."""
    state = json.loads((folder / "state.json").read_text())
    saved = load_torch_file(folder / "agent.pt", "agent checkpoint", ["policy", "actor_optimizer",
                                                                     "critic_optimizer"])
    model.policy.load_state_dict(saved["policy"])
    model.actor.optimizer.load_state_dict(saved["actor_optimizer"])
    model.critic.optimizer.load_state_dict(saved["critic_optimizer"])
    with np.load(folder / "replay.npz", allow_pickle=False) as z:
        rb = model.replay_buffer
        n = len(z["actions"])
        if n > rb.buffer_size:
            raise UserError(f"{folder / 'replay.npz'}: {n} transitions do not fit a buffer of "
                            f"{rb.buffer_size}", hint="give the run's --buffer-size")
        for f in BUFFER_FIELDS:
            getattr(rb, f)[:n] = z[f]
        if getattr(model, "expert_actions", None) is not None:
            model.expert_actions[:n] = z["expert_actions"]
        rb.pos, rb.full = int(z["pos"]), bool(z["full"])
    model.num_timesteps = int(state["env_steps"])
    model._n_updates = int(state["updates"])
    model._episode_num = int(state.get("episodes", 0))
    return state
