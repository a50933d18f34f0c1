"""A short S3K run trains the self-supervised term: warm-up and ramp shrink to fit ``--steps``, and the log
names the step where the term switches on."""

from __future__ import annotations

import pytest
import torch

from s3k.cli import main as cli_main
from s3k.config import TrainConfig
from s3k.detector import load_network

SHORT = ["--steps", "8", "--batch-labelled", "2", "--batch-unlabelled", "2", "--channels", "8,16",
         "--res-blocks", "1", "--val-every", "0", "--no-progress", "--threads", "1"]


@pytest.fixture(scope="module")
def dataset(tiny_dataset):
    return tiny_dataset


def test_warmup_and_ramp_shrink_to_the_steps():
    assert TrainConfig.from_flat(steps=200).unsup_schedule() == (100, 100)
    assert TrainConfig.from_flat(steps=8, warmup_steps=750, ramp_steps=250).unsup_schedule() == (6, 2)
    assert TrainConfig.from_flat(steps=3000).unsup_schedule() == (750, 750)  # long enough: as given
    assert TrainConfig.from_flat(steps=1500).unsup_schedule() == (750, 750)
    cfg = TrainConfig.from_flat(steps=200)
    assert [cfg.alpha_at(s) for s in (99, 100, 199)] == [0.0, 0.5 / 100, 0.5]


def test_a_short_s3k_run_switches_the_term_on_and_differs_from_labels_only(dataset, tmp_path):
    """The default warm-up (750) outlasts the 8 steps: the term switches on at step 5, the log says so, and
    the weights differ from the labels-only run's of the same seed."""
    assert cli_main(["train", str(dataset), "--out", str(tmp_path / "s3k"), *SHORT]) == 0
    assert cli_main(["train", str(dataset), "--out", str(tmp_path / "labels"), *SHORT, "--no-unsup"]) == 0
    log = (tmp_path / "s3k" / "train.log").read_text()
    assert ("self-supervised term: switches on at step 5, alpha reaches 0.5 at step 8 (--warmup-steps 750 "
            "and --ramp-steps 750 shrunk in proportion to fit the 8 steps)") in log
    assert "self-supervised term" not in (tmp_path / "labels" / "train.log").read_text()
    s3k, labels = (load_network(tmp_path / name)[0].state_dict() for name in ("s3k", "labels"))
    assert any(not torch.equal(s3k[k], labels[k]) for k in s3k)
