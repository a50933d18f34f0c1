"""Fine-tuning: ``s3k train --init-from RUN`` starts from another run's network instead of a new one."""

from __future__ import annotations

import json

import pytest
import torch
from helpers.interrupt import Killed, kill_after_three
from helpers.synthetic_rig import make_dataset

from s3k.base.errors import UserError
from s3k.cli import main as cli_main
from s3k.config import TrainConfig
from s3k.detector import load_network
from s3k.run_folder import RunFolder
from s3k.train import train
from s3k.train.presets import preset


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
    # in one command: the run's two passes, each at the learning rate it ended at
    again = tmp_path / "again"
    assert cli_main(["train", str(tiny_dataset), "--out", str(again), "--init-from", str(first),
                     "--steps", "1"]) == 0
    cfg = RunFolder(again).config()
    assert cfg.passes.two_pass and cfg.schedule.steps == 1 and cfg.passes.coarse_steps is None
    before = RunFolder(first).config()
    assert before is not None
    ended = pytest.approx(before.schedule.lr * cfg.schedule.lr_final)
    assert cfg.schedule.lr == cfg.passes.coarse_lr == ended
    assert (again / "two_pass.json").is_file()
    assert json.loads((again / "two_pass.json").read_text())["extent"] == extent[0]
    with pytest.raises(UserError, match="a two-pass run"):
        train(tiny_dataset, tmp_path / "one", config(steps=1), init_from=first)
    with pytest.raises(UserError, match="not a two-pass run"):
        train(tiny_dataset, tmp_path / "other", config(steps=1, **two), init_from=tmp_path / "tuned" / "fine")
    assert not (tmp_path / "one").exists() and not (tmp_path / "other").exists()


def printed_config(capsys, argv: list[str]) -> tuple[dict, str]:
    """The configuration ``s3k train ... --print-config`` resolves to, and what it said on stderr."""
    capsys.readouterr()
    assert cli_main(["train", *argv, "--print-config"]) == 0
    out = capsys.readouterr()
    return json.loads(out.out), out.err


def test_a_fine_tune_takes_the_runs_configuration_at_its_final_learning_rate(tiny_dataset, tmp_path, capsys):
    """``--init-from RUN`` alone: RUN's configuration, the learning rate RUN ended at (``lr x lr_final``), the
    self-supervised term on from the first step; an option given wins, and so does a ``--preset``."""
    first = tmp_path / "first"
    train(tiny_dataset, first, config(seed=4, lr=2e-3, lr_final=0.1, warmup_steps=2, ramp_steps=1, alpha=0.3))
    own = RunFolder(first).config()
    argv = [str(tiny_dataset), "--out", str(tmp_path / "tuned"), "--init-from", str(first)]
    cfg, said = printed_config(capsys, argv)
    assert cfg == own.replace(lr=2e-4, warmup_steps=0, ramp_steps=0).to_dict()
    assert f"fine-tuning {first}: its configuration (one pass)" in said
    assert "at the learning rate it ended at, 0.0002 (--lr 0.002 x --lr-final 0.1)" in said
    cfg, said = printed_config(capsys, [*argv, "--lr", "5e-4", "--steps", "7", "--warmup-steps", "1"])
    assert cfg == own.replace(lr=5e-4, steps=7, warmup_steps=1, ramp_steps=0).to_dict()
    assert "given here: --lr, --steps, --warmup-steps" in said
    cfg, said = printed_config(capsys, [*argv, "--preset", "box-fast"])
    assert cfg == preset("box-fast").to_dict()
    assert "the configuration is --preset box-fast's, not the run's" in said


def test_a_two_pass_fine_tune_continues_each_pass_at_its_final_learning_rate(tiny_dataset, tmp_path, capsys):
    """Of a two-pass run, the coarse pass's and the refining pass's final learning rates; ``--lr`` and
    ``--steps`` given alone are both passes', as in a run of their own."""
    run = RunFolder(tmp_path / "first")
    run.path.mkdir()
    own = preset("box-headline").replace(lr_final=0.1)  # coarse pass 1e-3 for 4000 steps, refining 5e-3
    run.write_config(own)
    argv = [str(tiny_dataset), "--out", str(tmp_path / "tuned"), "--init-from", str(run.path)]
    cfg, said = printed_config(capsys, argv)
    tuned = TrainConfig.from_flat(**cfg)
    assert cfg == own.replace(lr=5e-4, coarse_lr=1e-4, warmup_steps=0, ramp_steps=0).to_dict()
    assert (tuned.coarse().schedule.lr, tuned.refining().schedule.lr) == pytest.approx((1e-4, 5e-4))
    assert "the coarse pass at 0.0001 (0.001 x 0.1)" in said
    cfg, _ = printed_config(capsys, [*argv, "--lr", "3e-4", "--steps", "50"])
    tuned = TrainConfig.from_flat(**cfg)
    assert (tuned.coarse().schedule.lr, tuned.refining().schedule.lr) == (3e-4, 3e-4)
    assert (tuned.coarse().schedule.steps, tuned.refining().schedule.steps) == (50, 50)
    cfg, _ = printed_config(capsys, [*argv, "--coarse-lr", "2e-4", "--coarse-steps", "9"])
    tuned = TrainConfig.from_flat(**cfg)
    assert (tuned.coarse().schedule.lr, tuned.refining().schedule.lr) == (2e-4, pytest.approx(5e-4))
    assert tuned.coarse().schedule.steps == 9


def test_a_run_that_ended_at_a_learning_rate_of_zero_is_refused_in_one_line(tiny_dataset, tmp_path, capsys):
    run = RunFolder(tmp_path / "first")
    run.path.mkdir()
    run.write_config(preset("box-fast").replace(lr_final=0.0))
    argv = ["train", str(tiny_dataset), "--out", str(tmp_path / "tuned"), "--init-from", str(run.path)]
    assert cli_main([*argv, "--print-config"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "learning rate of 0 (--lr-final 0)" in err and "give --lr" in err
    assert cli_main(["train", str(tiny_dataset), "--out", str(tmp_path / "x"), "--init-from",
                     str(tmp_path / "nothing"), "--print-config"]) == 1
    assert "not a trained run" in capsys.readouterr().err
    capsys.readouterr()
    cfg, _ = printed_config(capsys, [*argv[1:], "--lr", "1e-4", "--coarse-lr", "1e-4"])
    assert cfg["lr"] == cfg["coarse_lr"] == 1e-4


def test_a_fine_tune_in_one_command_trains_from_the_runs_configuration(tiny_dataset, tmp_path, capsys):
    first = tmp_path / "first"
    train(tiny_dataset, first, config(seed=2, lr=2e-3, lr_final=0.5))
    tuned = tmp_path / "tuned"
    assert cli_main(["train", str(tiny_dataset), "--out", str(tuned), "--init-from", str(first),
                     "--steps", "2"]) == 0
    assert f"fine-tuning {first}: its configuration (one pass)" in capsys.readouterr().err
    expected = RunFolder(first).config().replace(steps=2, lr=1e-3, warmup_steps=0, ramp_steps=0)
    assert RunFolder(tuned).config().to_dict() == expected.to_dict()
    assert f"fine-tuning: the network starts from {first}" in (tuned / "train.log").read_text()
    assert load_network(tuned)[0] is not None


def test_a_killed_fine_tune_resumes_from_its_checkpoint_not_from_the_other_run(tiny_dataset, tmp_path):
    """A fine-tune stopped after its checkpoint at step 2 and resumed with ``--init-from`` still given (as a
    script repeats its command) continues from its own checkpoint: it ends where an uninterrupted fine-tune
    ends, not where one restarted from the other run's network would."""
    first = tmp_path / "first"
    train(tiny_dataset, first, config(seed=1))
    cfg = config(steps=4, checkpoint_every=2, seed=2)
    full = train(tiny_dataset, tmp_path / "full", cfg, init_from=first)
    with pytest.raises(Killed):
        train(tiny_dataset, tmp_path / "killed", cfg, init_from=first, progress=kill_after_three)
    assert not RunFolder(tmp_path / "killed").model.exists()
    resumed = train(tiny_dataset, tmp_path / "killed", cfg, init_from=first, resume=True)
    assert resumed.step == full.step == 4
    a, b = weights(tmp_path / "full"), weights(tmp_path / "killed")
    for name in a:
        assert torch.equal(a[name], b[name]), name
    assert "resumed from" in RunFolder(tmp_path / "killed").log.read_text()
