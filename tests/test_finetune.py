"""Fine-tuning: ``s3k train --init-from RUN`` starts from another run's network instead of a new one."""

from __future__ import annotations

import json

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


def test_a_two_pass_run_is_fine_tuned_pass_by_pass(tiny_dataset, tmp_path):
    """``s3k.train(..., init_from=)`` with two passes: each pass starts from its pass of the other run, and
    the crops keep that run's extent; a two-pass run does not start a one-pass one, nor the reverse."""
    two = dict(two_pass=True, coarse_size=32, crop_size=32)
    first = tmp_path / "first"
    train(tiny_dataset, first, config(seed=1, **two))
    tuned = tmp_path / "tuned"
    result = train(tiny_dataset, tuned, config(steps=1, lr=1e-12, crop_margin=2.0, **two), init_from=first)
    assert result.status == "done" and set(result.passes) == {"coarse", "fine"}
    for part in ("coarse", "fine"):
        a, b = weights(first / part), weights(tuned / part)
        for name in a:
            torch.testing.assert_close(b[name], a[name], rtol=0, atol=1e-6)
    extent = [json.loads((run / "two_pass.json").read_text())["extent"] for run in (first, tuned)]
    assert extent[0] == extent[1]  # the other run's crops, not those --crop-margin 2 would cut
    with pytest.raises(UserError, match="a two-pass run"):
        train(tiny_dataset, tmp_path / "one", config(steps=1), init_from=first)
    with pytest.raises(UserError, match="not a two-pass run"):
        train(tiny_dataset, tmp_path / "other", config(steps=1, **two), init_from=tmp_path / "tuned" / "fine")
    assert not (tmp_path / "one").exists() and not (tmp_path / "other").exists()
