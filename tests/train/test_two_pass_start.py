"""Starting and restarting ``s3k train --two-pass``: a failed start leaves nothing in the way of a retry,
``--resume`` takes the run's own options, and a crop extent larger than the images is warned about."""

from __future__ import annotations

import json
import shutil

from helpers.synthetic_rig import make_dataset

from s3k import cli
from s3k.config import REFERENCE_CROP, default_of
from s3k.data import Dataset
from s3k.detector import TWO_PASS_FILE
from s3k.run_folder import RunFolder
from s3k.train.two_pass import crop_rule_from_labels
from s3k.train.two_pass_start import crop_extent_warning

OPTIONS_FILE = RunFolder.OPTIONS

TINY = ["--steps", "3", "--coarse-size", "32", "--crop-size", "32", "--channels", "8,8", "--res_blocks", "1",
        "--val_every", "0", "--warmup_steps", "1", "--ramp_steps", "1", "--no-progress", "--threads", "1",
        "--rotation_deg", "15", "--coarse-rotation", "90"]


def _config(run, name):
    return json.loads((run / name / "config.json").read_text())["config"]


def test_a_failed_start_can_be_retried_and_resumed_without_repeating_options(tmp_path, capsys):
    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=0, test=2)
    run = tmp_path / "run"
    args = ["train", str(data), "--out", str(run), "--two-pass", *TINY]
    # S3K needs unlabelled frames: the coarse pass refuses before training, and no folder is left behind.
    assert cli.main(args) == 1
    assert "unlabelled" in capsys.readouterr().err
    assert not run.exists()
    # The folder such a start used to leave (only cpu.json) is not in the way, with or without --overwrite.
    for extra in ([], ["--overwrite"]):
        run.mkdir()
        (run / "cpu.json").write_text('{"coarse": 0.5}\n')
        assert cli.main([*args, *extra]) == 1
        err = capsys.readouterr().err
        assert "unlabelled" in err and "exists" not in err and "refusing" not in err
        assert not run.exists()
    # The retry with the option the error named trains both passes.
    assert cli.main([*args, "--no-unsup"]) == 0
    assert (run / TWO_PASS_FILE).is_file() and (run / OPTIONS_FILE).is_file()
    trained = {name: _config(run, name) for name in ("coarse", "fine")}
    assert trained["coarse"]["rotation_deg"] == 90 and trained["fine"]["rotation_deg"] == 15
    assert not trained["fine"]["unsup"] and trained["fine"]["steps"] == 3

    # Killed before the refining pass: --resume alone finishes it as the run was started.
    shutil.rmtree(run / "fine")
    (run / TWO_PASS_FILE).unlink()
    capsys.readouterr()
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--resume", "--no-progress"]) == 0
    assert "coarse pass: " in capsys.readouterr().out
    assert _config(run, "fine") == trained["fine"]
    # A run started before its options were recorded: they are read from its passes and crops.
    (run / OPTIONS_FILE).unlink()
    (run / "fine" / "model.pt").unlink()
    (run / TWO_PASS_FILE).unlink()
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--resume", "--no-progress"]) == 0
    assert (run / TWO_PASS_FILE).is_file()
    assert {k: v for k, v in _config(run, "fine").items() if k != "progress"} == \
        {k: v for k, v in trained["fine"].items() if k != "progress"}
    # Changing a setting on --resume is still refused by the pass it concerns.
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--resume", "--unsup"]) == 1
    assert "unsup" in capsys.readouterr().err


def test_the_default_crop_is_the_one_the_pixel_options_are_given_at():
    assert default_of("crop_size") == REFERENCE_CROP


def test_a_crop_extent_larger_than_the_images_is_warned_about(tmp_path):
    ds = Dataset.open(make_dataset(tmp_path / "d", size=64, labelled=4), cache="none")
    rule = crop_rule_from_labels(ds, size=32, margin=0.3)
    assert crop_extent_warning(ds, rule.extent, 32, 32) is None  # the object is small in the images
    text = crop_extent_warning(ds, 20 * rule.extent, 32, 32)
    assert text is not None
    assert f"the crops are {20 * rule.extent:g} m wide" in text and "larger than the whole image" in text
    assert "--crop-extent" in text
