"""Fine-tuning: ``s3k train --init-from RUN`` starts from another run's network instead of a new one."""

from __future__ import annotations

import pytest
import torch
from helpers.synthetic_rig import make_dataset

from s3k.cli import main as cli_main
from s3k.config import TrainConfig
from s3k.detector import load_network
from s3k.errors import UserError
from s3k.train import train


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data") / "ds", size=32, labelled=4, unlabelled=8, test=4)


def config(**over) -> TrainConfig:
    base = dict(steps=3, batch_labelled=2, batch_unlabelled=2, channels=(8, 16, 16), res_blocks=1,
                warmup_steps=1, ramp_steps=1, val_every=0, checkpoint_every=10, progress=False, threads=1)
    base.update(over)
    return TrainConfig.from_flat(**base)


def weights(run) -> dict[str, torch.Tensor]:
    model, _ = load_network(run)
    return {k: v for k, v in model.named_parameters()}


def test_a_fine_tuned_run_starts_from_the_other_runs_network(tiny_dataset, tmp_path):
    first = tmp_path / "first"
    train(tiny_dataset, first, config(seed=1))
    # a step at a negligible learning rate leaves the network where it started
    tuned = tmp_path / "tuned"
    assert cli_main(["train", str(tiny_dataset), "--out", str(tuned), "--init-from", str(first),
                     "--steps", "1", "--lr", "1e-12", "--channels", "8,16,16", "--res-blocks", "1",
                     "--val-every", "0", "--no-progress", "--threads", "1"]) == 0
    fresh = tmp_path / "fresh"
    train(tiny_dataset, fresh, config(steps=1, lr=1e-12))
    a, b, c = weights(first), weights(tuned), weights(fresh)
    for name in a:
        torch.testing.assert_close(b[name], a[name], rtol=0, atol=1e-6)
    assert any(not torch.allclose(c[name], a[name]) for name in a)
    assert f"fine-tuning: the network starts from {first}" in (tuned / "train.log").read_text()


def test_another_network_is_refused_before_anything_is_written(tiny_dataset, tmp_path):
    first = tmp_path / "first"
    train(tiny_dataset, first, config(steps=1))
    with pytest.raises(UserError, match="--init-from") as err:
        train(tiny_dataset, tmp_path / "other", config(steps=1, channels=(8, 8)), init_from=first)
    assert "differs" in str(err.value)
    assert not (tmp_path / "other").exists()
