"""Data-parallel training under torchrun: 2 CPU ranks (gloo) train and end with identical weights."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers.synthetic_rig import make_dataset

SCRIPT = textwrap.dedent(
    """
    import os, sys
    import torch
    import torch.distributed as dist
    from s3k.config import TrainConfig
    from s3k.train import train

    data, out, dump = sys.argv[1:4]
    dist.init_process_group("gloo")
    rank = dist.get_rank()
    cfg = TrainConfig.from_flat(steps=2, batch_labelled=2, batch_unlabelled=2, channels=(8, 16),
                                res_blocks=1, warmup_steps=0, ramp_steps=1, val_every=1, val_frames=2,
                                checkpoint_every=1, progress=False, threads=1, device="cpu")
    result = train(data, out, cfg)
    # the model of each rank, plus proof that the ranks saw different frames
    torch.save({"state": result.model.state_dict(), "step": result.step}, f"{dump}/rank{rank}.pt")
    dist.destroy_process_group()
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # two processes each importing torch: about 25 s on 2 busy cores
def test_two_ranks_identical_weights(tmp_path: Path):
    data = make_dataset(tmp_path / "ds", size=32, labelled=4, unlabelled=4, test=2)
    script = tmp_path / "ddp_train.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr",
           "127.0.0.1", "--master_port", str(_free_port()), str(script), str(data), str(tmp_path / "run"),
           str(tmp_path)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    r0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    r1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert r0["step"] == r1["step"] == 2
    init = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    for k, v in r0["state"].items():
        assert torch.equal(v, r1["state"][k]), k
    # only rank 0 writes the run folder, and it holds the trained weights
    assert (tmp_path / "run" / "model.pt").is_file()
    assert len(init["rng"]) == 2  # both ranks' random streams are checkpointed
    for k, v in r0["state"].items():
        assert torch.equal(v, init["model"][k]), k
    assert "DDP" in (tmp_path / "run" / "train.log").read_text()


def test_shards_are_disjoint_and_cover():
    import numpy as np

    from s3k.train import DistInfo, shard

    ids = np.arange(10)
    parts = [shard(ids, DistInfo(rank=r, world=3)) for r in range(3)]
    assert sorted(np.concatenate(parts).tolist()) == ids.tolist()
    assert all(len(set(a) & set(b)) == 0 for i, a in enumerate(parts) for b in parts[i + 1:])
    assert shard(ids[:2], DistInfo(rank=1, world=3)).tolist() == [0, 1]  # fewer frames than ranks: all
