"""Run folders written by the code before the two-pass options joined the configuration
(``tests/data/old_runs``, made by its ``make_old_runs.py`` at revision e7e42b1) still load, evaluate and
resume, and their configuration reads as today's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers.paths import OLD_RUNS as OLD
from helpers.synthetic_rig import make_dataset

from s3k import cli
from s3k.detector import Detector, load_network
from s3k.model import UNet
from s3k.run_folder import RunFolder


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    # the dataset the old runs were trained on (make_old_runs.py): the same tables, the same fingerprint
    return make_dataset(tmp_path_factory.mktemp("old") / "ds", size=48, labelled=4, unlabelled=4, test=2)


def _copy(name: str, tmp_path: Path) -> Path:
    return Path(shutil.copytree(OLD / name, tmp_path / name))


def test_an_old_two_pass_run_reads_as_a_configuration_of_today(tmp_path):
    run = RunFolder(_copy("two", tmp_path))
    assert "coarse_size" in json.loads(run.options_file.read_text())  # the options kept beside the config
    cfg = run.config()
    assert cfg is not None and cfg.passes.two_pass
    p = cfg.passes
    assert (p.coarse_size, p.coarse_steps, p.coarse_rotation, p.coarse_lr, p.coarse_stride) == \
        (32, 3, 90.0, 0.001, None)
    assert (p.crop_size, p.crop_margin, p.crop_extent, cfg.schedule.lr, cfg.schedule.steps) == \
        (32, 0.2, None, 0.002, 4)
    # each pass's configuration is the one the pass recorded
    for view, folder in ((cfg.coarse(), run.coarse), (cfg.refining(), run.fine)):
        assert view.to_dict() == {**view.to_dict(), **folder.read_record()["config"]}
    # older still: no options file, the configuration from the passes and the crop rule
    run.options_file.unlink()
    older = run.config()
    assert older is not None and older.coarse().to_dict() == cfg.coarse().to_dict()
    assert older.refining().to_dict() == cfg.refining().to_dict()
    assert older.passes.crop_extent == pytest.approx(json.loads(run.two_pass_file.read_text())["extent"])


def test_old_runs_load_and_evaluate(dataset, tmp_path, capsys):
    for name, passes in (("one", 1), ("two", 2)):
        run = _copy(name, tmp_path)
        detector = Detector.load(run)
        assert detector.keypoints == ["a", "b", "c"]
        # written before the encoder option: the U-Net, in the network and in the configuration
        net, _ = load_network(run / "coarse" if passes == 2 else run)
        assert type(net) is UNet and net.config.encoder == "unet"
        assert RunFolder(run).config().backbone.encoder == "unet"  # type: ignore[union-attr]
        assert RunFolder(run).is_complete() and RunFolder(run).is_two_pass() == (passes == 2)
        capsys.readouterr()
        assert cli.main(["evaluate", str(run), "--data", str(dataset), "--json"]) == 0
        metrics = json.loads(capsys.readouterr().out)
        assert metrics["n_frames"] == 2
        assert metrics["confidence"]["calibrated"] is False  # trained before runs were calibrated


def test_an_old_run_thresholds_its_raw_weights_and_says_so_once(dataset, tmp_path, caplog):
    """A run trained before confidences were calibrated: the confidence is the raw weight (the identity map),
    so --min-weight selects the views it selected before, and a threshold asked of it notes that once."""
    import logging

    from s3k.data import Dataset
    from s3k.readout import select_views

    run = _copy("one", tmp_path)
    ds = Dataset.open(dataset)
    ids = ds.frames("test")
    with caplog.at_level(logging.INFO, logger="s3k"):
        detector = Detector.load(run, "cpu")
        out = detector(ds.images(ids), ds.calibration(ids), min_weight=0.5)
        Detector.load(run, "cpu")(ds.images(ids), ds.calibration(ids), min_weight=0.5)
    assert caplog.text.count("has no confidence calibration") == 1
    assert detector.meta.calibration is None and out.confidence is out.weights
    assert out.used.equal(select_views(out.uv, out.weights, 0.5))


def test_an_old_one_pass_run_resumes_from_its_checkpoint(dataset, tmp_path):
    run = _copy("one", tmp_path)
    assert cli.main(["train", str(dataset), "--out", str(run), "--resume", "--steps", "6"]) == 0
    _, meta = load_network(run)
    doc = RunFolder(run).read_record()
    assert doc["config"]["steps"] == 6 and doc["history"][-1]["changed"] == {"steps": [4, 6]}
    assert json.loads((run / RunFolder.PROGRESS).read_text())["step"] == 6


def test_an_old_two_pass_run_resumes_its_refining_pass(dataset, tmp_path):
    """A two-pass run killed in its refining pass (its model not yet written) continues from the refining
    pass's checkpoint, on crops cut again from the recorded estimates, with the run's recorded options."""
    run = RunFolder(_copy("two", tmp_path))
    run.fine.model.unlink()
    run.two_pass_file.unlink()
    estimates = run.estimates.read_text()
    assert cli.main(["train", str(dataset), "--out", str(run.path), "--resume", "--steps", "6"]) == 0
    assert run.is_two_pass() and run.fine.model.is_file()
    assert json.loads(run.fine.progress.read_text())["step"] == 6
    assert json.loads(run.coarse.progress.read_text())["step"] == 3  # complete: not trained again
    assert run.estimates.read_text() == estimates
    fine = run.fine.read_record()
    assert fine["config"]["steps"] == 6 and fine["history"][-1]["changed"] == {"steps": [4, 6]}
    assert RunFolder(run.path).config().passes.coarse_rotation == 90.0  # recorded as today's
