"""Data-parallel training under torchrun: 2 CPU ranks (gloo) train what one process trains with the same
global batch, step by step, and a run stopped under torchrun resumes where an uninterrupted one goes."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers.paths import REPO
from helpers.synthetic_rig import make_dataset

from s3k.base.errors import UserError
from s3k.config import TrainConfig
from s3k.train import train
from s3k.train.distributed import DistInfo, check_batches, part

# Each job of the plan trains one run; rank r saves its losses per step and its final weights beside the run.
SCRIPT = textwrap.dedent(
    """
    import json, sys
    import torch
    import torch.distributed as dist
    from s3k.config import TrainConfig
    from s3k.train import train

    class Stop(Exception):
        pass

    data, work, plan = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    dist.init_process_group("gloo")
    rank = dist.get_rank()
    for job in plan:
        losses = []

        def progress(step, terms):
            losses.append(terms["loss"])
            if step == job["stop"]:
                raise Stop  # on every rank after the same step, as a kill would stop them

        try:
            result = train(data, f"{work}/{job['out']}", TrainConfig.from_flat(**job["cfg"]),
                           resume=job["resume"], progress=progress)
        except Stop:
            continue
        torch.save({"losses": losses, "state": result.model.state_dict(), "step": result.step},
                   f"{work}/{job['out']}-rank{rank}.pt")
    dist.destroy_process_group()
    """
)

# tiny network and images, float32, one thread, group norm (independent of how the batch is split); S3K with
# a teacher, so that every part of a step is compared
CONFIG = dict(steps=20, batch_labelled=4, batch_unlabelled=4, channels=(8, 16), res_blocks=1, norm="group",
              warmup_steps=2, ramp_steps=4, teacher_ema=0.5, val_every=10, val_frames=2, checkpoint_every=5,
              log_every=1, progress=False, threads=1, device="cpu", seed=1)
# Final weights: absolute, on weights of order 0.01-1 after 20 steps (rounding leaves about 1e-7). The heatmap
# head's bias is left out: a constant added to a heatmap's logits before the spatial softmax changes nothing,
# so its gradient is zero but for rounding, which Adam scales up to steps of the learning rate's size.
WEIGHT_TOL = 1e-5
UNSEEN = ("head.bias",)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(data: Path, work: Path, plan: list[dict]) -> None:
    script = work / "ddp_train.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr",
           "127.0.0.1", "--master_port", str(_free_port()), str(script), str(data), str(work),
           json.dumps(plan)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]


def _one_process(data: Path, out: Path, resume: bool = False) -> dict:
    losses: list[float] = []
    result = train(data, out, TrainConfig.from_flat(**CONFIG), resume=resume,
                   progress=lambda step, terms: losses.append(terms["loss"]))
    return {"losses": losses, "state": result.model.state_dict(), "step": result.step}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    """One process's 20 steps; two ranks' 20 steps; two ranks stopped after 10 of 20 steps, then resumed by a
    new torchrun; the same stopped run resumed by one process."""
    work = tmp_path_factory.mktemp("ddp")
    data = make_dataset(work / "ds", size=32, labelled=6, unlabelled=6, test=2)
    job = {"cfg": CONFIG, "resume": False, "stop": None}
    _torchrun(data, work, [{**job, "out": "two"}, {**job, "out": "stopped", "stop": 10}])
    shutil.copytree(work / "stopped", work / "stopped-copy")
    _torchrun(data, work, [{**job, "out": "stopped", "resume": True}])
    load = lambda name: torch.load(work / name, weights_only=True)  # noqa: E731
    return {"work": work, "one": _one_process(data, work / "one"),
            "one_resumed": _one_process(data, work / "stopped-copy", resume=True),
            "two": [load(f"two-rank{r}.pt") for r in range(2)],
            "resumed": [load(f"stopped-rank{r}.pt") for r in range(2)]}


def _max_abs(a: dict, b: dict) -> float:
    """The largest difference between two networks' weights (but those the heatmaps do not depend on)."""
    return max(float((a[k].double() - b[k].double()).abs().max()) for k in a if k not in UNSEEN)


# two launches of two processes each importing torch and two trainings here: 31-83 s on 2 busy cores
@pytest.mark.slow
def test_two_ranks_train_what_one_process_trains(runs):
    one, (r0, r1) = runs["one"], runs["two"]
    assert r0["step"] == r1["step"] == one["step"] == 20
    # the loss each rank logs is the whole batch's, the one one process logs
    assert len(r0["losses"]) == len(one["losses"]) == 20
    for step, (a, b) in enumerate(zip(r0["losses"], one["losses"]), 1):
        assert abs(a - b) <= 1e-4 * abs(b), (step, a, b)
    assert r1["losses"] == r0["losses"]
    for k, v in r0["state"].items():
        assert torch.equal(v, r1["state"][k]), k  # DDP keeps the ranks' weights identical
    assert _max_abs(r0["state"], one["state"]) < WEIGHT_TOL
    # only rank 0 writes the run folder, and it holds the trained weights and both ranks' (one) stream
    run = runs["work"] / "two"
    saved = torch.load(run / "checkpoint.pt", weights_only=True)
    for k, v in r0["state"].items():
        assert torch.equal(v, saved["model"][k]), k
    assert len(saved["rng"]) == 2 and torch.equal(saved["rng"][0]["gen"], saved["rng"][1]["gen"])
    assert "DDP" in (run / "train.log").read_text()


@pytest.mark.slow  # shares the trainings above
def test_resume_under_torchrun_ends_where_an_uninterrupted_run_ends(runs):
    two, resumed, one_resumed = runs["two"][0], runs["resumed"], runs["one_resumed"]
    assert resumed[0]["step"] == 20 and len(resumed[0]["losses"]) == 10  # steps 11 to 20, after a new start
    assert resumed[0]["losses"] == two["losses"][10:]
    for r in range(2):
        for k, v in two["state"].items():
            assert torch.equal(v, resumed[r]["state"][k]), (r, k)
    # two ranks' checkpoint, resumed by one process: the same shared stream, so the same run within rounding
    assert one_resumed["step"] == 20
    for a, b in zip(one_resumed["losses"], two["losses"][10:]):
        assert abs(a - b) <= 1e-4 * abs(b)
    assert _max_abs(one_resumed["state"], two["state"]) < WEIGHT_TOL


def test_each_rank_takes_its_contiguous_part_of_the_global_batch():
    images, labels = torch.arange(6), torch.arange(6) * 10
    got = part((images, None, labels), DistInfo(rank=1, world=3))
    assert got[0].tolist() == [2, 3] and got[1] is None and got[2].tolist() == [20, 30]
    assert part((images, labels), DistInfo()) == (images, labels)  # one process: the batch itself
    check_batches(4, 6, True, 2)
    check_batches(4, 3, False, 2)  # without S3K the unlabelled batch is not drawn


def test_a_batch_the_ranks_cannot_split_is_refused_before_anything_is_written(tiny_dataset, tmp_path,
                                                                               monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")  # as torchrun --nproc-per-node 2 sets it
    cfg = TrainConfig.from_flat(**{**CONFIG, "batch_labelled": 3})
    with pytest.raises(UserError, match=r"^--batch-labelled 3 does not split over the 2 processes .*; give "
                                        r"--batch-labelled a multiple of 2$"):
        train(tiny_dataset, tmp_path / "run", cfg)
    assert not (tmp_path / "run").exists()
