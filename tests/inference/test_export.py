"""Tests of ``s3k export``: ONNX and TorchScript files reproduce the PyTorch detector to 1e-4."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.tiny_detector import RUN_SIZE as SIZE
from helpers.tiny_detector import make_run, save_run

from s3k import cli
from s3k.detector import DetectorMeta, load_network
from s3k.inference.export import META_KEY, TRACE_BATCH, export_detector, run_exported, verification_images
from s3k.model import UNetConfig, detect
from s3k.readout import window_cells
from s3k.readout.heatmaps import confidence_weight

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")




@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("export") / "run")


def _inputs(n: int = 5, seed: int = 7) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, SIZE[1], SIZE[0], generator=g).numpy()


@pytest.mark.parametrize("fmt, suffix", [("onnx", ".onnx"), ("torchscript", ".pt")])
@pytest.mark.parametrize("with_moments", [False, True])
def test_export_matches_pytorch(run_dir, tmp_path, fmt, suffix, with_moments):
    report = export_detector(run_dir, fmt, tmp_path / f"detector{suffix}", with_moments=with_moments)
    assert report.ok and report.path.is_file()
    assert set(report.max_diff) == set(report.outputs)
    assert report.outputs == (["logits", "means", "confidence"] if with_moments else ["logits"])

    # Independently of the verification inside export: another batch size than the traced one, and the
    # reference from the model as loaded (BatchNorm not folded) through s3k.model.detect.
    images = _inputs(5)
    assert len(images) != TRACE_BATCH
    got = run_exported(report.path, fmt, images)
    model, meta = load_network(run_dir)
    with torch.no_grad():
        logits, means, var = detect(model, torch.from_numpy(images)[None], meta.stride,
                                   window_cells(meta.sigma, meta.stride))
    h, w = SIZE[1] // 2, SIZE[0] // 2
    assert got[0].shape == (5, 3, h, w)
    np.testing.assert_allclose(got[0], logits[0].numpy(), atol=1e-4, rtol=0)
    assert np.ptp(got[0]) > 1.0  # not a trivially flat output
    if with_moments:
        assert got[1].shape == (5, 3, 2) and got[2].shape == (5, 3)
        np.testing.assert_allclose(got[1], means[0].numpy(), atol=1e-4, rtol=0)
        np.testing.assert_allclose(got[2], confidence_weight(var[0], meta.sigma).numpy(), atol=1e-4, rtol=0)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_exported_files_carry_the_metadata(run_dir, tmp_path):
    _, meta = load_network(run_dir)
    onnx_path = export_detector(run_dir, "onnx", tmp_path / "d.onnx", with_moments=True).path
    import onnx

    props = {p.key: p.value for p in onnx.load(str(onnx_path)).metadata_props}
    doc = json.loads(props[META_KEY])
    assert doc["keypoints"] == meta.keypoints and doc["image_size"] == list(SIZE)
    assert doc["outputs"] == ["logits", "means", "confidence"]

    ts_path = export_detector(run_dir, "torchscript", tmp_path / "d.pt").path
    files = {f"{META_KEY}.json": ""}
    torch.jit.load(str(ts_path), _extra_files=files)
    doc = json.loads(files[f"{META_KEY}.json"])
    assert doc["stride"] == meta.stride and doc["sigma"] == meta.sigma and doc["outputs"] == ["logits"]


def test_export_verifies_on_the_runs_dataset(tmp_path):
    from helpers.synthetic_rig import make_dataset

    data = make_dataset(tmp_path / "data", size=32, labelled=1, unlabelled=1, test=1)
    run = make_run(tmp_path / "run", dataset=str(data), norm="group")
    meta = load_network(run)[1]
    images, source = verification_images(meta, str(data))
    assert str(data) in source and images.shape == (6, 3, SIZE[1], SIZE[0])
    assert images.dtype == np.float32 and 0 <= images.min() and images.max() <= 1
    report = export_detector(run, "onnx", tmp_path / "d.onnx")
    assert report.ok and str(data) in report.inputs and report.num_images == 6


def test_cli_prints_difference_and_fails_on_a_wrong_file(run_dir, tmp_path, capsys, monkeypatch):
    out = tmp_path / "d.onnx"
    assert cli.main(["export", str(run_dir), "--format", "onnx", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "max |difference| from PyTorch" in text and "logits" in text

    # A file that does not reproduce the model (one weight changed after export) must be rejected.
    from helpers.onnx_files import corrupt_exports

    corrupt_exports(monkeypatch)
    assert cli.main(["export", str(run_dir), "--format", "onnx", "--out", str(out), "--overwrite"]) == 1
    captured = capsys.readouterr()
    assert "does not reproduce" in captured.err and "max |difference|" in captured.out


def test_export_errors(run_dir, tmp_path, capsys):
    with pytest.raises(ValueError, match="--format"):
        export_detector(run_dir, "tflite", tmp_path / "x")
    missing = str(tmp_path / "missing")
    assert cli.main(["export", missing, "--format", "onnx", "--out", str(tmp_path / "x")]) == 1
    assert "missing" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_load_exported_runs_torchscript_only_when_asked(run_dir, tmp_path):
    """A TorchScript file is a program: load_exported refuses it unless the caller asks for TorchScript."""
    from s3k.base.errors import UserError
    from s3k.inference.export import load_exported

    ts = export_detector(run_dir, "torchscript", tmp_path / "d.pt").path
    with pytest.raises(UserError, match="TorchScript export, which runs code .* fmt='torchscript'") as err:
        load_exported(ts)
    assert "\n" not in str(err.value)
    assert load_exported(ts, "torchscript").keypoints == ["a", "b", "c"]
    onnx_path = export_detector(run_dir, "onnx", tmp_path / "d.onnx").path
    assert load_exported(onnx_path).keypoints == ["a", "b", "c"]
    # a two-pass export's JSON naming TorchScript files: refused too unless asked
    doc = {"format": "s3k-exported-two-pass/1", "extent": 0.3, "size": 40, "margin": 0.1,
           "runtime": "torchscript", "coarse": "d.pt", "fine": "d.pt"}
    (tmp_path / "two.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match="TorchScript export"):
        load_exported(tmp_path / "two.json")
    (tmp_path / "junk.onnx").write_bytes(b"\x00not a model at all\xff" * 10)
    with pytest.raises(UserError, match="junk.onnx: not an ONNX file"):
        load_exported(tmp_path / "junk.onnx")


@pytest.mark.parametrize("edit, match", [
    (lambda d: "{not json", "not a two-pass export of s3k \\(not JSON"),
    (lambda d: {**d, "format": "other"}, "format 'other', expected"),
    (lambda d: {k: v for k, v in d.items() if k != "fine"}, "field\\(s\\) fine missing"),
    (lambda d: {**d, "extent": float("inf")}, "field 'extent' is inf; expected a finite positive number"),
    (lambda d: {**d, "extent": -1.0}, "field 'extent' is -1.0"),
    (lambda d: {**d, "size": 12.5}, "field 'size' is 12.5; expected a finite positive whole number"),
    (lambda d: {**d, "margin": "x"}, "field 'margin' is 'x'"),
    (lambda d: {**d, "coarse": "../outside.onnx"},
     "field 'coarse' is '../outside.onnx'; expected the name of a file beside it"),
    (lambda d: {**d, "fine": "/etc/hostname"}, "field 'fine' is '/etc/hostname'"),
    (lambda d: {**d, "fine": "absent.onnx"}, "field 'fine' names absent.onnx, which is not in"),
])
def test_load_exported_checks_the_two_pass_json(run_dir, tmp_path, edit, match):
    from s3k.base.errors import UserError
    from s3k.inference.export import load_exported

    folder = tmp_path / "export"
    folder.mkdir()
    export_detector(run_dir, "onnx", folder / "d.onnx")
    (tmp_path / "outside.onnx").write_bytes((folder / "d.onnx").read_bytes())
    good = {"format": "s3k-exported-two-pass/1", "extent": 0.3, "size": 40, "margin": 0.1, "runtime": "onnx",
            "coarse": "d.onnx", "fine": "d.onnx"}
    path = folder / "d.json"
    edited = edit(good)
    path.write_text(edited if isinstance(edited, str) else json.dumps(edited))
    with pytest.raises(UserError, match=match) as err:
        load_exported(path)
    assert "\n" not in str(err.value) and "d.json" in str(err.value)


def test_export_of_a_checkpoint_is_checked_against_that_checkpoint(tmp_path, capsys):
    """``--checkpoint`` exports that file's network: its 3D check compares with the same network (it was
    compared with the run's final model, and failed by millimetres while the logits matched)."""
    import shutil

    from helpers.synthetic_rig import make_dataset

    data = make_dataset(tmp_path / "data", size=32, labelled=1, unlabelled=1, test=2)
    run = make_run(tmp_path / "run", dataset=str(data), norm="group")
    other = make_run(tmp_path / "other", dataset=str(data), norm="group")  # same meta, other weights
    state = torch.load(other / "model.pt", weights_only=True)
    state["model"] = {k: v + 0.05 * torch.randn_like(v) if v.is_floating_point() else v
                      for k, v in state["model"].items()}
    torch.save(state, run / "early.pt")
    shutil.rmtree(other)
    code = cli.main(["export", str(run), "--format", "onnx", "--out", str(tmp_path / "d.onnx"),
                     "--checkpoint", "early.pt"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "max 3D difference from PyTorch's detector on 4 frames" in captured.out


def test_a_failed_3d_check_is_named(run_dir, tmp_path, capsys, monkeypatch):
    """When the 3D points fail while every output is within --tolerance, the error names the 3D check and
    its figure, not the outputs' tolerance."""
    import s3k.inference.export as export

    monkeypatch.setattr(export, "_verify_points", lambda *args, **kwargs: (10.6, 8))
    assert cli.main(["export", str(run_dir), "--format", "onnx", "--out", str(tmp_path / "d.onnx")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert ("3D points differ from PyTorch's detector's by 10.6 mm on 8 frames (3D tolerance 0.1 mm)"
            in err), err
    assert "0.0001" not in err and "output logits" not in err


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_an_exported_detector_applies_the_runs_confidence_calibration(tmp_path):
    """The calibration travels in the export's metadata and its read-out applies it, as the run's does."""
    from helpers.synthetic_rig import rig

    from s3k.detector import Detector
    from s3k.geometry import Cameras
    from s3k.inference.export import load_exported
    from s3k.readout import ConfidenceMap

    calibration = ConfidenceMap((0.1, 0.5, 0.9), (0.55, 0.7, 0.95), 4.0, 60)
    meta = DetectorMeta(keypoints=["a", "b", "c"], cameras=["cam0", "cam1", "cam2", "cam3"], image_size=SIZE,
                        stride=2, sigma=2.0, model=UNetConfig(channels=(8, 16, 16), res_blocks=1).to_dict(),
                        calibration=calibration.to_dict())
    run = save_run(tmp_path / "run", meta, seed=1, head_std=0.5)
    path = export_detector(run, "onnx", tmp_path / "d.onnx").path
    exported = load_exported(path)
    assert exported.meta.calibration == calibration.to_dict()
    K, dist, R, t = rig(32)
    K[:, 0, 2] = (SIZE[0] - 1) / 2
    cams = Cameras.from_numpy(K, dist, R, t)
    frames = (_inputs(8).reshape(2, 4, 3, SIZE[1], SIZE[0]).transpose(0, 1, 3, 4, 2) * 255).astype(np.uint8)
    got, want = exported(frames, cams), Detector.load(run, "cpu")(frames, cams)
    torch.testing.assert_close(got.confidence, calibration(got.weights))
    assert not torch.allclose(got.confidence, got.weights)
    np.testing.assert_allclose(got.confidence.numpy(), want.confidence.numpy(), atol=1e-4)
