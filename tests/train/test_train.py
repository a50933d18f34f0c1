"""Training: a 2-step run, learning, exact resume after a kill, non-finite losses, sampling, configuration."""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.interrupt import Killed, kill_after_three
from helpers.synthetic_rig import KEYPOINTS, make_dataset

import s3k.train.loop as loop_module
from s3k.base.errors import UserError
from s3k.cli import main as cli_main
from s3k.cli.config_options import add_config_arguments, config_from_args
from s3k.config import TrainConfig, config_from_dict, leaf_fields
from s3k.data.frames import FrameStore, open_dataset
from s3k.detector import load_network
from s3k.model import UNet, UNetConfig
from s3k.train import draw_batch, train


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data") / "ds", size=32, labelled=4, unlabelled=8, test=4)


def tiny_config(**over) -> TrainConfig:
    base = dict(steps=4, batch_labelled=2, batch_unlabelled=2, channels=(8, 16, 16), res_blocks=1,
                warmup_steps=1, ramp_steps=2, val_every=2, val_frames=4, checkpoint_every=2, log_every=1,
                progress=False, threads=1)
    base.update(over)
    return TrainConfig.from_flat(**base)


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
    model, meta = load_network(run)
    assert meta.keypoints == KEYPOINTS and meta.image_size == (32, 32) and meta.stride == 2
    assert meta.sigma == pytest.approx(TrainConfig().model.sigma * 2)
    logits = model(torch.rand(4, 3, 32, 32))
    assert logits.shape == (4, 3, 16, 16) and torch.isfinite(logits).all()
    assert json.loads((run / "progress.json").read_text())["step"] == 2  # for monitors such as s3k demo
    ckpt = torch.load(run / "checkpoint.pt", weights_only=True)
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
    real = loop_module.compute_losses

    def spy(model, lab, unl, cfg, alpha, wd_model, rule, teacher=None, precision="float32"):
        seen.append((unl is None, alpha))
        return real(model, lab, unl, cfg, alpha, wd_model, rule, teacher, precision)

    monkeypatch.setattr(loop_module, "compute_losses", spy)
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

    with pytest.raises(Killed):
        train(tiny_dataset, tmp_path / "killed", cfg, progress=kill_after_three)
    assert torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=True)["step"] == 2
    assert not (tmp_path / "killed" / "model.pt").exists()
    resumed = train(tiny_dataset, tmp_path / "killed", cfg, resume=True)
    assert resumed.step == 4
    a, b = _state(full), _state(resumed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    opt_a = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=True)
    opt_b = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=True)
    for pa, pb in zip(opt_a["optimizer"]["state"].values(), opt_b["optimizer"]["state"].values()):
        assert torch.equal(pa["exp_avg"], pb["exp_avg"]) and torch.equal(pa["exp_avg_sq"], pb["exp_avg_sq"])
    assert opt_a["scheduler"] == opt_b["scheduler"]
    assert "resumed from" in (tmp_path / "killed" / "train.log").read_text()


def _inject_nan(monkeypatch, bad_calls):
    real = loop_module.compute_losses
    calls = {"n": 0}

    def poisoned(*args):
        loss, terms = real(*args)
        i = calls["n"]
        calls["n"] += 1
        if i in bad_calls:
            loss = loss * float("nan")
        return loss, terms

    monkeypatch.setattr(loop_module, "compute_losses", poisoned)


def test_nonfinite_step_is_reported_and_skipped(tiny_dataset, tmp_path, monkeypatch):
    _inject_nan(monkeypatch, {1})
    result = train(tiny_dataset, tmp_path / "run", tiny_config(steps=3, val_every=0, checkpoint_every=1))
    assert result.status == "done" and result.step == 3
    log = (tmp_path / "run" / "train.log").read_text()
    assert "step 1: non-finite loss" in log and "step skipped" in log
    assert all(torch.isfinite(v).all() for v in result.model.state_dict().values() if v.is_floating_point())
    ckpt = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())


def test_skipped_step_leaves_model_unchanged(tiny_dataset, tmp_path, monkeypatch):
    """Only non-finite steps: nothing moves (weights and normalization statistics), then a clean stop."""
    _inject_nan(monkeypatch, set(range(100)))
    cfg = tiny_config(steps=10, val_every=0, checkpoint_every=100, max_nonfinite=3)
    result = train(tiny_dataset, tmp_path / "run", cfg)
    assert result.status == "nonfinite" and result.step == 3
    torch.manual_seed(cfg.execution.seed)
    fresh = UNet(len(KEYPOINTS), UNetConfig(channels=cfg.model.channels, res_blocks=cfg.model.res_blocks))
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
    for _, f, _ in leaf_fields(TrainConfig):
        assert f"--{f.name.replace('_', '-')}" in text, f.name
    assert "(default: 750; >= 0)" in text and "labels-only steps before the self-supervised term" in text
    assert "--no-unsup" in text


def test_config_file_then_command_line(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text('steps = 123\nalpha = 0.8\nchannels = [8, 16]\nunsup = false\n')
    cfg = config_from_args(_parser().parse_args(["--config", str(toml), "--alpha", "0.3"]), TrainConfig)
    s = cfg.self_supervision
    assert (cfg.schedule.steps, s.alpha, cfg.model.channels, s.unsup) == (123, 0.3, (8, 16), False)
    js = tmp_path / "c.json"
    js.write_text(json.dumps({"stepz": 3}))
    with pytest.raises(ValueError, match=r"c\.json.*stepz"):
        config_from_args(_parser().parse_args(["--config", str(js)]), TrainConfig)
    with pytest.raises(SystemExit):  # refused as the command line is parsed
        _parser().parse_args(["--steps", "abc"])
    with pytest.raises(ValueError, match="'steps'.*abc"):  # and from a file
        js.write_text(json.dumps({"steps": "abc"}))
        config_from_args(_parser().parse_args(["--config", str(js)]), TrainConfig)


def test_flat_and_nested_configuration():
    cfg = TrainConfig.from_flat(steps=12, channels=[8, 16], unsup=False)
    assert (cfg.schedule.steps, cfg.model.channels, cfg.self_supervision.unsup) == (12, (8, 16), False)
    flat = cfg.to_dict()
    assert flat["channels"] == [8, 16] and len(flat) == len(leaf_fields(TrainConfig))
    assert config_from_dict(TrainConfig, flat) == cfg  # what config.json holds reads back
    assert config_from_dict(TrainConfig, {"schedule": {"steps": 12}, "unsup": False}).schedule.steps == 12
    assert cfg.replace(lr=0.1).schedule.lr == 0.1 and cfg.schedule.lr == TrainConfig().schedule.lr
    with pytest.raises(UserError, match="stepz"):
        TrainConfig.from_flat(stepz=3)
    names = [f.name for _, f, _ in leaf_fields(TrainConfig)]
    assert len(names) == len(set(names))  # unique across sections: the flat form is unambiguous



def test_a_configuration_is_read_and_set_only_through_its_sections():
    """A field is an attribute of its section alone: a flat name neither reads nor sets one, so that a type
    checker sees every read, and a stray write fails at once instead of being lost."""
    cfg = TrainConfig.from_flat(steps=12)
    for _, f, _ in leaf_fields(TrainConfig):
        assert not hasattr(cfg, f.name), f.name
    with pytest.raises(AttributeError):
        cfg.steps = 3  # type: ignore[attr-defined]
    assert cfg.schedule.steps == 12
    cfg.schedule.steps = 3
    assert cfg.replace(lr=0.5).schedule.steps == 3 and cfg.to_dict()["steps"] == 3

def test_alpha_schedule_and_validation():
    cfg = TrainConfig.from_flat(warmup_steps=10, ramp_steps=4, alpha=0.8)
    assert [cfg.alpha_at(s) for s in (0, 9, 10, 11, 13, 100)] == pytest.approx([0, 0, 0.2, 0.4, 0.8, 0.8])
    assert TrainConfig.from_flat(unsup=False).alpha_at(10_000) == 0
    with pytest.raises(UserError, match="batch_labelled"):
        TrainConfig.from_flat(batch_labelled=0).validate()


KILL_SCRIPT = """
import os, signal, sys
from s3k.config import TrainConfig
from s3k.train import train

data, out, steps, kill_at = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
cfg = TrainConfig.from_flat(steps=steps, batch_labelled=2, batch_unlabelled=2, channels=(8, 16),
                            res_blocks=1, warmup_steps=1, ramp_steps=2, val_every=0, checkpoint_every=2,
                            progress=False, threads=1)


def kill(step, terms):
    if step == kill_at:  # the process kills itself: no clean-up of any kind runs after this step
        os.kill(os.getpid(), signal.SIGKILL)


train(data, out, cfg, progress=kill)
"""


def test_resume_after_sigkill_matches_uninterrupted(tiny_dataset, tmp_path):
    """A training process SIGKILLed at step 3 (by itself, so the step is known), then ``--resume``d, ends
    with the weights of an uninterrupted run."""
    import os
    import signal
    import subprocess
    import sys

    script = tmp_path / "kill.py"
    script.write_text(KILL_SCRIPT)
    run, full = tmp_path / "killed", tmp_path / "full"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(script), str(tiny_dataset), str(run), "4", "3"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert torch.load(run / "checkpoint.pt", weights_only=True)["step"] == 2  # the step-3 state died with it
    assert not (run / "model.pt").exists()
    options = ["--steps", "4", "--batch_labelled", "2", "--batch_unlabelled", "2", "--channels", "8,16",
               "--res_blocks", "1", "--warmup_steps", "1", "--ramp_steps", "2", "--val_every", "0",
               "--checkpoint_every", "2", "--no-progress", "--threads", "1"]
    assert cli_main(["train", str(tiny_dataset), "--out", str(run), "--resume"]) == 0
    assert cli_main(["train", str(tiny_dataset), "--out", str(full), *options]) == 0
    a = torch.load(full / "model.pt", weights_only=True)["model"]
    b = torch.load(run / "model.pt", weights_only=True)["model"]
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def _labelled_error(net, meta, dataset_path) -> float:
    from s3k.detector import OnePassDetector
    from s3k.inference.evaluate import evaluate_store

    ds = open_dataset(dataset_path, meta.image_size)
    store = FrameStore(ds, ds.frames("labelled"), labels=True, points=True)
    net.eval()
    metrics, _ = evaluate_store(OnePassDetector(net, meta), store)
    return metrics["rms_px"]


def test_a_few_dozen_steps_lower_the_error(tmp_path):
    """40 labels-only steps on the dot scene bring the 2D error on the labelled frames well below the
    untrained network's (fixed seeds: the same numbers on every run; measured 3.8 -> 1.3 px)."""
    data = make_dataset(tmp_path / "ds", size=32, labelled=6, unlabelled=0, test=0, seed=3)
    cfg = tiny_config(steps=40, unsup=False, augment=False, val_every=0, checkpoint_every=40, lr=3e-2,
                      lr_final=1.0, batch_labelled=4)
    result = train(data, tmp_path / "run", cfg)
    torch.manual_seed(cfg.execution.seed)  # the network train() starts from
    untrained = UNet(len(KEYPOINTS), UNetConfig.from_dict(result.meta.model))
    before = _labelled_error(untrained, result.meta, data)
    after = _labelled_error(result.model, result.meta, data)
    assert after < 0.6 * before, (before, after)


# ---------------------------------------------------------------------------------------------------------
# sampling


def test_training_holds_each_image_once(tiny_dataset, tmp_path, monkeypatch):
    """The stores training fills (labelled, unlabelled, validation) serve their images from the dataset's
    own image cache, not from copies, and serve exactly the dataset's images in frame order."""
    stores: list[FrameStore] = []

    class Recorded(FrameStore):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            stores.append(self)

    monkeypatch.setattr(loop_module, "FrameStore", Recorded)
    train(tiny_dataset, tmp_path / "run", tiny_config(steps=1, val_every=1))
    assert len(stores) == 3
    ds = stores[0].dataset
    cache, _ = ds.cached_images(ds.frames())
    for store in stores:
        assert store.dataset is ds and store.preloaded
        assert store.image_array is not None and store.image_array.data_ptr() == cache.ctypes.data
        assert store.image_array.shape == cache.shape  # the whole cache: a view, not a per-store copy
        batch = store.get(np.arange(len(store))[::-1].copy())
        np.testing.assert_array_equal(batch.frame_ids, store.frame_ids[::-1])
        np.testing.assert_array_equal(batch.images.numpy(), ds.images(batch.frame_ids))


@pytest.mark.parametrize("cache", ["disk", "memory", "none"])
def test_preloaded_store_copies_only_without_a_dataset_cache(tiny_dataset, cache):
    ds = open_dataset(tiny_dataset, cache=cache)
    ids = ds.frames("unlabelled")[::-1]
    store = FrameStore(ds, ids, chunk=3)
    shared = ds.cached_images(ids)
    assert store.image_array is not None
    if shared is None:  # cache="none": the store's copy is the only one
        assert cache == "none" and store.image_array.shape[0] == len(ids)
    else:
        assert store.image_array.data_ptr() == shared[0].ctypes.data
    np.testing.assert_array_equal(store.get(np.arange(len(ids))).images.numpy(), ds.images(ids))
    assert not FrameStore(ds, ids, preload_mb=0).preloaded


def test_draw_batch_distinct_reproducible_and_covering(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    store = FrameStore(ds, ds.frames("unlabelled"), labels=False)  # 8 frames
    ids = set(store.frame_ids.tolist())

    def draw(seed, n, distinct):
        return draw_batch(store, n, torch.Generator().manual_seed(seed), distinct).frame_ids.tolist()

    for seed in range(20):
        assert len(set(draw(seed, 5, True))) == 5  # labelled batches: no frame twice
    assert draw(7, 5, True) == draw(7, 5, True) and draw(7, 5, False) == draw(7, 5, False)
    assert draw(7, 5, True) != draw(8, 5, True)
    assert len(draw(0, 20, True)) == 20  # more than the store holds: repeats are allowed then
    gen = torch.Generator().manual_seed(0)
    seen = {i for _ in range(30) for i in draw_batch(store, 2, gen, True).frame_ids.tolist()}
    assert seen == ids  # every frame is reachable
    batch = draw_batch(store, 3, torch.Generator().manual_seed(1), False)
    assert batch.images.shape == (3, 4, 32, 32, 3) and batch.images.dtype == torch.uint8
    np.testing.assert_array_equal(batch.images.numpy(), ds.images(batch.frame_ids))


def test_mean_pairwise_distance():
    from s3k.train import mean_pairwise_distance

    X = torch.tensor([[[0.0, 0, 0], [3, 4, 0], [0, 0, 0]]])
    assert mean_pairwise_distance(X, torch.tensor([[True, True, True]])) == pytest.approx((5 + 0 + 5) / 3)
    assert mean_pairwise_distance(X, torch.tensor([[True, True, False]])) == pytest.approx(5.0)
    assert math.isnan(mean_pairwise_distance(X, torch.tensor([[True, False, False]])))


def test_labelled_distances_are_the_rigid_layout(tiny_dataset, tmp_path):
    """The labelled frames' triangulated keypoints give the synthetic triangle's side lengths; a dataset
    whose labels triangulate nothing is refused by --layout-tol, naming it."""
    from helpers.synthetic_rig import LAYOUT

    from s3k.train import labelled_distances

    ds = open_dataset(tiny_dataset)
    d = labelled_distances(ds, ds.frames("labelled")).numpy()
    truth = np.linalg.norm(LAYOUT[:, None] - LAYOUT[None], axis=-1)
    off = ~np.eye(3, dtype=bool)
    np.testing.assert_allclose(d[off], truth[off], rtol=2e-3)
    assert np.isnan(np.diag(d)).all()
    one = make_dataset(tmp_path / "one-keypoint", labelled=2, unlabelled=2, test=1)
    labels = (one / "labels.csv").read_text().splitlines()
    (one / "labels.csv").write_text("\n".join([labels[0]] + [r for r in labels[1:] if ",a," in r]) + "\n")
    assert np.isnan(labelled_distances(open_dataset(one), np.arange(2)).numpy()).all()
    with pytest.raises(UserError, match="--layout-tol"):
        train(one, tmp_path / "run", tiny_config(steps=1, layout_tol=0.2))
    assert not (tmp_path / "run").exists()
    train(one, tmp_path / "run", tiny_config(steps=1))  # without it the same labels train
    held = train(tiny_dataset, tmp_path / "held", tiny_config(steps=2, warmup_steps=0, ramp_steps=0,
                                                             layout_tol=0.2))
    assert held.status == "done"
    # the read-out of the trained detector holds its keypoints to the same layout (the saved meta)
    _, meta = load_network(tmp_path / "held")
    assert meta.layout_tol == 0.2
    np.testing.assert_allclose(np.asarray(meta.layout, dtype=float), d, equal_nan=True)
    _, plain = load_network(tmp_path / "run")
    assert plain.layout is None and plain.layout_distances is None


def test_collapse_warning(tiny_dataset, tmp_path):
    """A network that puts every keypoint at one point triggers the collapse warning once S3K is on."""
    from s3k.train import labelled_layout, validate

    result = train(tiny_dataset, tmp_path / "run", tiny_config(steps=1, val_every=0))
    net = result.model
    with torch.no_grad():  # uniform heatmaps: every keypoint at the image centre
        net.head.weight.zero_()
        net.head.bias.zero_()
    ds = open_dataset(tiny_dataset)
    ref = labelled_layout(ds, ds.frames("labelled"))
    assert 0.05 < ref < 0.2  # the synthetic triangle's size, metres
    store = FrameStore(ds, ds.frames("test"), labels=True, points=True)
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler = Keep()
    logger = logging.getLogger("s3k.train")
    logger.addHandler(handler)
    try:
        out = validate(net, result.meta, store, torch.device("cpu"), ref, tiny_config(warmup_steps=0), 5)
        assert out["layout_ratio"] < 0.05
        assert any("possible collapse" in r for r in records)
        records.clear()
        validate(net, result.meta, store, torch.device("cpu"), ref, tiny_config(warmup_steps=100, steps=200),
                 5)
        assert not any("possible collapse" in r for r in records)  # still in the labels-only warm-up
    finally:
        logger.removeHandler(handler)


def test_teacher_follows_the_network_and_resumes_exactly(tiny_dataset, tmp_path):
    """--teacher-ema: the teacher is saved in the checkpoint, lags the network as an exponential moving
    average, and a killed run resumes to the same network and teacher as an uninterrupted one."""
    cfg = tiny_config(steps=4, checkpoint_every=2, teacher_ema=0.5)
    full = train(tiny_dataset, tmp_path / "full", cfg)
    state = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=True)
    net, teacher = state["model"], state["teacher"]
    name = next(k for k, v in net.items() if v.ndim == 4)
    assert not torch.equal(net[name], teacher[name])  # it lags
    assert torch.equal(net[next(k for k in net if "running_mean" in k)],
                       teacher[next(k for k in net if "running_mean" in k)])

    with pytest.raises(Killed):
        train(tiny_dataset, tmp_path / "killed", cfg, progress=kill_after_three)
    resumed = train(tiny_dataset, tmp_path / "killed", cfg, resume=True)
    a, b = _state(full), _state(resumed)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    again = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=True)["teacher"]
    for k in teacher:
        assert torch.equal(teacher[k], again[k]), k
    # without a teacher the checkpoint has none; a decay of 1 would never move it
    train(tiny_dataset, tmp_path / "plain", tiny_config(steps=2, checkpoint_every=2))
    assert "teacher" not in torch.load(tmp_path / "plain" / "checkpoint.pt", weights_only=True)
    with pytest.raises(UserError, match="teacher_ema"):
        tiny_config(teacher_ema=1.0).validate()


def test_teacher_update_is_the_moving_average():
    from s3k.detector import DetectorMeta
    from s3k.train.distributed import DistInfo
    from s3k.train.loop import _Loop

    cfg = tiny_config(teacher_ema=0.75)
    meta = DetectorMeta(keypoints=["a"], cameras=["c"], image_size=(32, 32), stride=2, sigma=3.0,
                        model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict(), units="m",
                        source_image_size=(32, 32))
    loop = _Loop(cfg, meta, torch.device("cpu"), DistInfo(), Path("."))
    before = [p.detach().clone() for p in loop.teacher.parameters()]
    with torch.no_grad():
        for p in loop.net.parameters():
            p.add_(1.0)
    loop.update_teacher()
    for t, b in zip(loop.teacher.parameters(), before):
        torch.testing.assert_close(t, b + 0.25)


def test_bfloat16_training_keeps_float32_heatmaps_and_learns(tiny_dataset, tmp_path):
    """--precision bfloat16: the network runs under autocast, its heatmap head and losses stay float32, the
    run finishes with finite weights and writes which arithmetic it used."""
    from s3k.model import UNet, UNetConfig

    net = UNet(3, UNetConfig(channels=(8, 16), res_blocks=1))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        logits = net(torch.rand(2, 3, 32, 32))
    assert logits.dtype == torch.float32
    result = train(tiny_dataset, tmp_path / "bf16", tiny_config(precision="bfloat16", steps=3, val_every=0))
    assert result.status == "done"
    assert all(torch.isfinite(p).all() for p in result.model.parameters())
    assert "(bfloat16)" in (tmp_path / "bf16" / "train.log").read_text()
    with pytest.raises(UserError, match="precision"):
        tiny_config(precision="half").validate()


def test_frames_held_on_another_device_are_drawn_there_once(tiny_dataset):
    """FrameStore.to: the stores of one dataset cache share one copy on the device, and batches come from
    it (the 'meta' device stands in for a GPU: shapes and placement without data)."""
    from s3k.data.frames import FrameStore, open_dataset

    ds = open_dataset(tiny_dataset)
    labelled = FrameStore(ds, ds.frames("labelled"), labels=True).to("meta")
    unlabelled = FrameStore(ds, ds.frames("unlabelled")).to("meta")
    assert labelled.image_array is unlabelled.image_array  # one copy of the cache
    batch = labelled.get(np.array([0, 2]))
    assert batch.images.device.type == "meta" and batch.images.shape[:2] == (2, len(ds.cameras))
    assert batch.labels_uv.device.type == "meta" and batch.cams.K.device.type == "meta"
    assert FrameStore(ds, ds.frames("test"), preload_mb=0).to("meta").image_array is None  # read per batch


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")
def test_training_on_the_gpu_holds_frames_there_in_bfloat16(tiny_dataset, tmp_path):
    result = train(tiny_dataset, tmp_path / "gpu", tiny_config(device="cuda", steps=3, val_every=2,
                                                                 precision="auto"))
    assert result.status == "done"
    log = (tmp_path / "gpu" / "train.log").read_text()
    assert "cuda" in log and ("(bfloat16)" in log) == torch.cuda.is_bf16_supported()
