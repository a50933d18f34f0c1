"""Training: a 2-step run, exact resume after a kill, non-finite losses, configuration handling."""

from __future__ import annotations

import argparse
import json
import math

import pytest
import torch
from synthetic_rig import KEYPOINTS, make_dataset

import s3k.train as train_module
from s3k.cli import main as cli_main
from s3k.config import (
    TrainConfig,
    add_config_arguments,
    config_from_args,
)
from s3k.run import load_detector
from s3k.train import train


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data") / "ds", size=32, labelled=4, unlabelled=8, test=4)


def tiny_config(**over) -> TrainConfig:
    base = dict(steps=4, batch_labelled=2, batch_unlabelled=2, channels=(8, 16, 16), res_blocks=1,
                warmup_steps=1, ramp_steps=2, val_every=2, val_frames=4, checkpoint_every=2, log_every=1,
                progress=False, threads=1)
    base.update(over)
    return TrainConfig(**base)


def test_two_step_cli_run(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    code = cli_main(["train", str(tiny_dataset), "--out", str(run), "--steps", "2", "--batch-labelled", "2",
                     "--batch_unlabelled", "2", "--channels", "8,16,16", "--warmup_steps", "0",
                     "--val-every", "1", "--val_frames", "2", "--no-progress", "--threads", "1"])
    assert code == 0
    for name in ("config.json", "checkpoint.pt", "model.pt", "train.log"):
        assert (run / name).is_file(), name
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    saved = json.loads((run / "config.json").read_text())
    assert saved["config"]["steps"] == 2 and saved["config"]["channels"] == [8, 16, 16]
    model, meta = load_detector(run)
    assert meta.keypoints == KEYPOINTS and meta.image_size == (32, 32) and meta.stride == 2
    assert meta.sigma == pytest.approx(TrainConfig().sigma * 2)
    logits = model(torch.rand(4, 3, 32, 32))
    assert logits.shape == (4, 3, 16, 16) and torch.isfinite(logits).all()
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ckpt["step"] == 2
    log = (run / "train.log").read_text()
    assert "step 1 validation" in log and "rms_px" in log
    # the same folder again without --resume is refused
    capsys.readouterr()
    assert cli_main(["train", str(tiny_dataset), "--out", str(run), "--steps", "2", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("s3k train: error: ") and str(run) in err[0]


def test_labels_only_baseline_draws_no_unlabelled_batch(tiny_dataset, tmp_path, monkeypatch):
    seen = []
    real = train_module.compute_losses

    def spy(model, lab, unl, cfg, alpha, wd_model):
        seen.append((unl is None, alpha))
        return real(model, lab, unl, cfg, alpha, wd_model)

    monkeypatch.setattr(train_module, "compute_losses", spy)
    result = train(tiny_dataset, tmp_path / "base", tiny_config(unsup=False, steps=3, val_every=0))
    assert result.status == "done" and seen == [(True, 0.0)] * 3
    seen.clear()
    train(tiny_dataset, tmp_path / "s3k", tiny_config(steps=3, val_every=0, warmup_steps=1, ramp_steps=2))
    assert seen == [(True, 0.0), (False, 0.25), (False, 0.5)]


def _state(result):
    return {k: v.clone() for k, v in result.model.state_dict().items()}


def test_resume_after_kill_continues_identically(tiny_dataset, tmp_path):
    cfg = tiny_config(steps=4, checkpoint_every=2)
    full = train(tiny_dataset, tmp_path / "full", cfg)

    class Killed(Exception):
        pass

    def kill_after_three(step, terms):
        if step == 3:
            raise Killed

    with pytest.raises(Killed):
        train(tiny_dataset, tmp_path / "killed", cfg, callback=kill_after_three)
    assert torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=False)["step"] == 2
    assert not (tmp_path / "killed" / "model.pt").exists()
    resumed = train(tiny_dataset, tmp_path / "killed", cfg, resume=True)
    assert resumed.step == 4
    a, b = _state(full), _state(resumed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    opt_a = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=False)
    opt_b = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=False)
    for pa, pb in zip(opt_a["optimizer"]["state"].values(), opt_b["optimizer"]["state"].values()):
        assert torch.equal(pa["exp_avg"], pb["exp_avg"]) and torch.equal(pa["exp_avg_sq"], pb["exp_avg_sq"])
    assert opt_a["scheduler"] == opt_b["scheduler"]
    assert "resumed from" in (tmp_path / "killed" / "train.log").read_text()


def _inject_nan(monkeypatch, bad_calls):
    real = train_module.compute_losses
    calls = {"n": 0}

    def poisoned(*args):
        loss, terms = real(*args)
        i = calls["n"]
        calls["n"] += 1
        if i in bad_calls:
            loss = loss * float("nan")
        return loss, terms

    monkeypatch.setattr(train_module, "compute_losses", poisoned)


def test_nonfinite_step_is_reported_and_skipped(tiny_dataset, tmp_path, monkeypatch):
    _inject_nan(monkeypatch, {1})
    result = train(tiny_dataset, tmp_path / "run", tiny_config(steps=3, val_every=0, checkpoint_every=1))
    assert result.status == "done" and result.step == 3
    log = (tmp_path / "run" / "train.log").read_text()
    assert "step 1: non-finite loss" in log and "step skipped" in log
    assert all(torch.isfinite(v).all() for v in result.model.state_dict().values() if v.is_floating_point())
    ckpt = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())


def test_skipped_step_leaves_model_unchanged(tiny_dataset, tmp_path, monkeypatch):
    """Only non-finite steps: nothing moves (weights and normalization statistics), then a clean stop."""
    _inject_nan(monkeypatch, set(range(100)))
    cfg = tiny_config(steps=10, val_every=0, checkpoint_every=100, max_nonfinite=3)
    result = train(tiny_dataset, tmp_path / "run", cfg)
    assert result.status == "nonfinite" and result.step == 3
    torch.manual_seed(cfg.seed)
    fresh = train_module.UNet(len(KEYPOINTS), train_module.UNetConfig(channels=cfg.channels,
                                                                        res_blocks=cfg.res_blocks))
    for (k, a), b in zip(fresh.state_dict().items(), result.model.state_dict().values()):
        assert torch.equal(a, b), k
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
    assert "consecutive non-finite" in (tmp_path / "run" / "train.log").read_text()


def test_cli_exit_status_after_nonfinite_stop(tiny_dataset, tmp_path, monkeypatch):
    _inject_nan(monkeypatch, set(range(100)))
    code = cli_main(["train", str(tiny_dataset), "--out", str(tmp_path / "r"), "--steps", "5",
                     "--max_nonfinite", "2", "--channels", "8,16", "--no-progress", "--val_every", "0"])
    assert code == 1


# ---------------------------------------------------------------------------------------------------------
# configuration


def _parser():
    p = argparse.ArgumentParser()
    add_config_arguments(p, TrainConfig)
    return p


def test_help_shows_every_field_with_doc_and_default():
    text = _parser().format_help()
    import dataclasses

    for f in dataclasses.fields(TrainConfig):
        assert f"--{f.name}" in text, f.name
    assert "(default: 750)" in text and "labels-only steps before the self-supervised term" in text
    assert "--no-unsup" in text


def test_config_file_then_command_line(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text('steps = 123\nalpha = 0.8\nchannels = [8, 16]\nunsup = false\n')
    cfg = config_from_args(_parser().parse_args(["--config", str(toml), "--alpha", "0.3"]))
    assert (cfg.steps, cfg.alpha, cfg.channels, cfg.unsup) == (123, 0.3, (8, 16), False)
    js = tmp_path / "c.json"
    js.write_text(json.dumps({"stepz": 3}))
    with pytest.raises(ValueError, match=r"c\.json.*stepz"):
        config_from_args(_parser().parse_args(["--config", str(js)]))
    with pytest.raises(ValueError, match="'steps'.*abc"):
        config_from_args(_parser().parse_args(["--steps", "abc"]))


def test_alpha_schedule_and_validation():
    cfg = TrainConfig(warmup_steps=10, ramp_steps=4, alpha=0.8)
    assert [cfg.alpha_at(s) for s in (0, 9, 10, 11, 13, 100)] == pytest.approx([0, 0, 0.2, 0.4, 0.8, 0.8])
    assert TrainConfig(unsup=False).alpha_at(10_000) == 0
    with pytest.raises(ValueError, match="batch_labelled"):
        TrainConfig(batch_labelled=0).validate()


@pytest.mark.slow  # three training processes: about 20 s
def test_resume_after_sigkill_matches_uninterrupted(tiny_dataset, tmp_path):
    """A real kill (SIGKILL of the training process) followed by --resume gives the uninterrupted weights."""
    import os
    import signal
    import subprocess
    import sys
    import time

    args = ["--steps", "40", "--batch_labelled", "2", "--batch_unlabelled", "2", "--channels", "8,16",
            "--res_blocks", "1", "--warmup_steps", "2", "--ramp_steps", "2", "--val_every", "0",
            "--checkpoint_every", "1", "--no-progress", "--threads", "1"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "s3k.cli", "train", str(tiny_dataset), "--out", str(run), *args]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            if (run / "checkpoint.pt").exists():
                time.sleep(0.3)
                break
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    killed_at = torch.load(run / "checkpoint.pt", weights_only=False)["step"]
    assert 1 <= killed_at < 40 and not (run / "model.pt").exists()
    quiet = dict(env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    subprocess.run([*cmd, "--resume"], **quiet)
    full = tmp_path / "full"
    subprocess.run([sys.executable, "-m", "s3k.cli", "train", str(tiny_dataset), "--out", str(full), *args],
                   **quiet)
    a = torch.load(full / "model.pt", weights_only=False)["model"]
    b = torch.load(run / "model.pt", weights_only=False)["model"]
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_mean_pairwise_distance():
    from s3k.train import mean_pairwise_distance

    X = torch.tensor([[[0.0, 0, 0], [3, 4, 0], [0, 0, 0]]])
    assert mean_pairwise_distance(X, torch.tensor([[True, True, True]])) == pytest.approx((5 + 0 + 5) / 3)
    assert mean_pairwise_distance(X, torch.tensor([[True, True, False]])) == pytest.approx(5.0)
    assert math.isnan(mean_pairwise_distance(X, torch.tensor([[True, False, False]])))


def test_collapse_warning(tiny_dataset, tmp_path):
    """A network that puts every keypoint at one point triggers the collapse warning once S3K is on."""
    import logging

    from s3k.frames import FrameStore, open_dataset
    from s3k.train import labelled_layout, validate

    result = train(tiny_dataset, tmp_path / "run", tiny_config(steps=1, val_every=0))
    net = result.model
    with torch.no_grad():  # uniform heatmaps: every keypoint at the image centre
        net.head.weight.zero_()
        net.head.bias.zero_()
    ds = open_dataset(tiny_dataset)
    ref = labelled_layout(FrameStore(ds, ds.frames("labelled"), labels=True))
    assert 0.05 < ref < 0.2  # the synthetic triangle's size, metres
    store = FrameStore(ds, ds.frames("test"), labels=True, points=True)
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler = Keep()
    train_module.log.addHandler(handler)
    try:
        out = validate(net, result.meta, store, torch.device("cpu"), ref, tiny_config(warmup_steps=0), 5)
        assert out["layout_ratio"] < 0.05
        assert any("possible collapse" in r for r in records)
        records.clear()
        validate(net, result.meta, store, torch.device("cpu"), ref, tiny_config(warmup_steps=100), 5)
        assert not any("possible collapse" in r for r in records)  # still in the labels-only warm-up
    finally:
        train_module.log.removeHandler(handler)
