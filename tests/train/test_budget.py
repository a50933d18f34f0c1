"""A training that cannot fit in memory is refused from its configuration, in one line, before any file is
written; the estimate (``s3k.budget``) is checked against what a real training step holds."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers.paths import REPO as ROOT

import s3k.budget as budget
from s3k.base.memory import available_memory
from s3k.budget import activation_elements, footprint, unet_parameters
from s3k.cli import main as cli_main
from s3k.config import TrainConfig
from s3k.model import UNet, UNetConfig
from s3k.train import train

GIB = 2**30
QUICK = ["--no-progress", "--threads", "1", "--val-every", "0"]


@pytest.fixture(scope="module")
def dataset(tiny_dataset):
    return tiny_dataset


@pytest.mark.parametrize("channels, res_blocks, stride, norm, keypoints", [
    ((16, 32, 32, 32), 2, 2, "batch", 3), ((8, 16), 0, 1, "none", 1), ((8, 16, 24), 3, 4, "group", 5)])
def test_parameter_count_is_the_networks(channels, res_blocks, stride, norm, keypoints):
    net = UNet(keypoints, UNetConfig(channels=channels, res_blocks=res_blocks, stride=stride, norm=norm))
    assert unet_parameters(channels, res_blocks, stride, keypoints, norm) == sum(
        p.numel() for p in net.parameters())


def test_activation_estimate_bounds_what_a_real_step_saves(dataset, tmp_path):
    """Every tensor autograd saves for the backward pass of one real training step (labelled and unlabelled
    batches, both losses), counted once per storage: the estimate is at least that and at most twice it (it
    adds 25% for the backward pass's transient gradients, and counts each layer's output generously)."""
    cfg = TrainConfig.from_flat(steps=1, batch_labelled=2, batch_unlabelled=2, warmup_steps=0, ramp_steps=0,
                                val_every=0, progress=False, threads=1, augment=False, image_size=64)
    saved: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        storage = t.untyped_storage()
        saved[storage.data_ptr()] = storage.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        train(dataset, tmp_path / "run", cfg)
    estimate = footprint(cfg, cameras=4, keypoints=3, source_size=(32, 32)).activations
    measured = sum(saved.values())
    assert measured <= estimate <= 2 * measured, (measured, estimate)


PEAK = textwrap.dedent("""
    import json, sys
    import torch
    from s3k.config import TrainConfig
    from s3k.train import train
    from s3k.budget import footprint
    torch.set_num_threads(1)
    cfg = TrainConfig.from_flat(steps=1, batch_labelled=4, batch_unlabelled=4, warmup_steps=0, ramp_steps=0,
                                val_every=0, progress=False, threads=1, augment=False, preload_mb=0,
                                image_size=192)
    def status(name):
        for line in open("/proc/self/status"):
            if line.startswith(name + ":"):
                return int(line.split()[1]) * 1024
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # the peak resident size (VmHWM) starts again from the resident size now
    before = status("VmRSS")
    train(sys.argv[1], sys.argv[2], cfg)
    after = status("VmHWM")
    need = footprint(cfg, cameras=4, keypoints=3, source_size=(32, 32)).total
    print(json.dumps({"measured": after - before, "estimate": need}))
""")


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK),
                    reason="needs Linux's /proc/self/clear_refs")
def test_estimate_bounds_the_peak_memory_of_a_training_process(dataset, tmp_path):
    """The peak resident memory a fresh process adds while it trains one step of 4 + 4 frames of 4 cameras at
    192 px (its peak reset as training starts, so the imports' own peak is not counted): the estimate is at
    least that, so a refusal refuses only what would not have fitted, and at most twice it, so what fits is
    not refused for want of much more memory."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", PEAK, str(dataset), str(tmp_path / "run")], env=env,
                          capture_output=True, text=True, check=True)
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["measured"] <= figures["estimate"] <= 2 * figures["measured"], figures


def test_available_memory_honours_an_address_space_limit():
    """Under ``ulimit -v`` the memory available is what the limit leaves, not the machine's."""
    limit = 3 * GIB

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    done = subprocess.run([sys.executable, "-c", "from s3k.base.memory import available_memory; "
                           "print(available_memory())"], env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, check=True, preexec_fn=limited)
    assert 0 < int(done.stdout) < limit
    assert available_memory() is not None


def refused(capsys, argv: list[str], *needles: str) -> str:
    """Run the command; assert it fails (1, or argparse's 2 for a value out of its range) with one error line
    holding every needle."""
    capsys.readouterr()
    try:
        code = cli_main(argv)
    except SystemExit as exc:
        code = exc.code
    assert code in (1, 2)
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in captured.err, err
    assert err[0].startswith("s3k train: error: "), err[0]
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    return err[0]


def files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.parametrize("options, memory, named", [
    (["--image-size", "1000000"], None, "--image-size"),
    (["--image-size", "60000"], 4 * GIB, "--image-size"),
    (["--batch-labelled", "100000000"], None, "--batch-labelled"),
    (["--stride", "3"], None, "--stride"),
    (["--channels", "99999999,99999999"], None, "--channels"),
    (["--channels", "4096,4096,4096,4096"], 4 * GIB, "--channels"),
    (["--res-blocks", "100000"], None, "--res-blocks"),
    (["--steps", "99999999999999999999999"], None, "--steps"),
])
def test_impossible_training_is_refused_before_anything_is_written(capsys, monkeypatch, dataset, tmp_path,
                                                                   options, memory, named):
    if memory is not None:  # a machine (or control group) with 4 GB
        monkeypatch.setattr(budget, "available_memory", lambda: memory)
    before = files(dataset)
    refused(capsys, ["train", str(dataset), "--out", str(tmp_path / "run"), *QUICK, *options], named)
    assert not (tmp_path / "run").exists()
    assert files(dataset) == before


def test_a_dataset_declaring_huge_images_is_refused_naming_its_image_size(capsys, dataset, tmp_path):
    huge = tmp_path / "huge"
    huge.mkdir()
    for name in os.listdir(dataset):
        (huge / name).symlink_to(dataset / name)
    meta = json.loads((dataset / "s3k.json").read_text())
    (huge / "s3k.json").unlink()
    (huge / "s3k.json").write_text(json.dumps({**meta, "image_size": [10**9, 10**9]}))
    refused(capsys, ["train", str(huge), "--out", str(tmp_path / "run"), *QUICK], "--image-size",
            "1000000000x1000000000")
    refused(capsys, ["train", str(huge), "--out", str(tmp_path / "run"), *QUICK, "--image-size", "64"],
            f"image_size in {huge}/s3k.json")
    assert not (tmp_path / "run").exists()


def test_the_messages_estimate_is_the_footprint():
    cfg = TrainConfig.from_flat(image_size=96)
    need = footprint(cfg, cameras=4, keypoints=3, source_size=(1280, 1024), frames=(10, 2000, 100))
    per_image = activation_elements(cfg.model.channels, cfg.model.res_blocks, cfg.model.stride, 3, (96, 76))
    assert need.activations == int(budget.SLACK * 4 * per_image * 8 * 4)
    with pytest.raises(ValueError, match="available; lower --preload-mb"):
        budget.check_fits(cfg, cameras=4, keypoints=3, source_size=(1280, 1024), frames=(10, 2000, 100),
                          where="d", available=need.total - 1)
    budget.check_fits(cfg, cameras=4, keypoints=3, source_size=(1280, 1024), frames=(10, 2000, 100),
                      where="d", available=need.total)
