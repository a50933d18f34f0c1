"""What ``s3k train`` refuses before writing anything, ``--resume``'s checks and history, and crafted pickles.

Every refusal goes through ``s3k.cli.main``: one line ``s3k train: error: ...`` naming the culprit, exit 1.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from helpers.files import contents
from helpers.synthetic_rig import make_dataset

from s3k.base.errors import UserError
from s3k.cli import main as cli_main
from s3k.detector import load_network
from s3k.train import read_checkpoint_step

TINY = ["--steps", "2", "--batch_labelled", "2", "--batch_unlabelled", "2", "--channels", "8,16",
        "--res_blocks", "1", "--warmup_steps", "0", "--val_every", "0", "--checkpoint_every", "1",
        "--no-progress", "--threads", "1"]


@pytest.fixture(scope="module")
def dataset(tiny_dataset):
    return tiny_dataset


@pytest.fixture(scope="module")
def finished_run(dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "run"
    assert cli_main(["train", str(dataset), "--out", str(run), *TINY]) == 0
    return run


def refused(capsys, argv: list[str], *needles: str) -> str:
    """Run the command; assert exit 1 and one error line holding every needle; return the line."""
    capsys.readouterr()
    assert cli_main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    line = err[0]
    assert line.startswith(f"s3k {argv[0]}: error: "), line
    for needle in needles:
        assert needle in line, (needle, line)
    return line


def test_existing_run_without_resume(capsys, dataset, finished_run):
    refused(capsys, ["train", str(dataset), "--out", str(finished_run), *TINY], str(finished_run), "--resume",
            "--overwrite")


def test_out_is_a_file(capsys, dataset, tmp_path):
    target = tmp_path / "file.txt"
    target.write_text("x")
    refused(capsys, ["train", str(dataset), "--out", str(target), *TINY], str(target), "is a file")
    assert target.read_text() == "x"


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_out_in_read_only_folder(capsys, dataset):
    """A folder where no one, root included, can create the run: refused before training, naming it."""
    out = Path("/proc/s3k-no-such-run/run")
    refused(capsys, ["train", str(dataset), "--out", str(out), *TINY], str(out), "/proc is not writable",
            "--out")


@pytest.mark.skipif(os.geteuid() == 0, reason="root may create files in a folder without write permission")
def test_out_in_folder_without_write_permission(capsys, dataset, tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        refused(capsys, ["train", str(dataset), "--out", str(folder / "run"), *TINY], str(folder),
                "not writable")
    finally:
        folder.chmod(0o755)
    assert list(folder.iterdir()) == []


def test_no_usable_label(capsys, tmp_path):
    """Labels in one camera only: nothing can be triangulated, so no supervised target exists."""
    data = make_dataset(tmp_path / "one-view", size=32, labelled=3, unlabelled=3, test=0, label_cameras=1)
    refused(capsys, ["train", str(data), "--out", str(tmp_path / "run"), *TINY], str(data),
            "none of the 3 labelled frames")
    assert not (tmp_path / "run").exists()


def test_s3k_without_unlabelled_frames_names_no_unsup(capsys, tmp_path):
    data = make_dataset(tmp_path / "no-unl", size=32, labelled=3, unlabelled=0, test=0)
    refused(capsys, ["train", str(data), "--out", str(tmp_path / "run"), *TINY], "unlabelled", "--no-unsup")
    assert not (tmp_path / "run").exists()
    assert cli_main(["train", str(data), "--out", str(tmp_path / "run"), *TINY, "--no-unsup"]) == 0


def test_overwrite_replaces_a_run_and_keeps_other_files(dataset, tmp_path):
    run = tmp_path / "run"
    assert cli_main(["train", str(dataset), "--out", str(run), *TINY]) == 0
    (run / "notes.txt").write_text("mine")
    assert cli_main(["train", str(dataset), "--out", str(run), *TINY, "--steps", "1", "--overwrite"]) == 0
    assert read_checkpoint_step(run / "checkpoint.pt") == 1
    assert (run / "notes.txt").read_text() == "mine"
    history = json.loads((run / "config.json").read_text())["history"]
    assert [h["event"] for h in history] == ["created"]


# ---------------------------------------------------------------------------------------------------------
# --resume


def _copy_run(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_resume_refuses_an_incompatible_change_and_leaves_config_untouched(capsys, dataset, finished_run,
                                                                           tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    before = (run / "config.json").read_bytes()
    refused(capsys, ["train", str(dataset), "--out", str(run), "--resume", "--channels", "8,32"],
            "channels", "8,32", "8,16")
    for flag, fix in ((["--lr", "0.5"], "--lr 0.001"), (["--seed", "3"], "--seed 0"),
                      (["--no-unsup"], "--unsup"), (["--stride", "4"], "--stride 2")):
        refused(capsys, ["train", str(dataset), "--out", str(run), "--resume", *flag], fix)
    assert (run / "config.json").read_bytes() == before
    # and a plain --resume still works afterwards
    assert cli_main(["train", str(dataset), "--out", str(run), "--resume"]) == 0


def test_resume_refuses_another_dataset(capsys, finished_run, tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    before = (run / "config.json").read_bytes()
    other = make_dataset(tmp_path / "other", size=32, labelled=3, unlabelled=3, test=2, seed=5)
    refused(capsys, ["train", str(other), "--out", str(run), "--resume"], "fingerprint", str(other))
    assert (run / "config.json").read_bytes() == before


def test_resume_records_allowed_changes(dataset, finished_run, tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    argv = ["train", str(dataset), "--out", str(run), "--resume", "--steps", "3", "--threads", "2"]
    assert cli_main(argv) == 0
    doc = json.loads((run / "config.json").read_text())
    assert doc["config"]["steps"] == 3 and read_checkpoint_step(run / "checkpoint.pt") == 3
    created, resumed = doc["history"]
    assert created["event"] == "created" and resumed["event"] == "resumed"
    assert resumed["changed"] == {"steps": [2, 3], "threads": [1, 2]}
    assert resumed["command"].startswith("s3k train ") and "--steps 3" in resumed["command"]


def test_resume_of_a_finished_run_writes_nothing(capsys, dataset, finished_run, tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    before = contents(run)
    capsys.readouterr()
    assert cli_main(["train", str(dataset), "--out", str(run), "--resume", "--threads", "2"]) == 0
    assert "complete at step 2: nothing to train" in capsys.readouterr().out
    assert contents(run) == before  # no history entry, log line, TensorBoard file or checkpoint
    # it is still checked as a resume: another setting is refused, more steps continue it
    refused(capsys, ["train", str(dataset), "--out", str(run), "--resume", "--lr", "0.5"], "--lr 0.001")
    assert cli_main(["train", str(dataset), "--out", str(run), "--resume", "--steps", "3"]) == 0
    assert read_checkpoint_step(run / "checkpoint.pt") == 3


def test_old_flat_config_json_still_resumes(dataset, finished_run, tmp_path):
    """A run whose config.json predates the dataset identity and history is resumed (names checked)."""
    run = _copy_run(finished_run, tmp_path / "run")
    doc = json.loads((run / "config.json").read_text())
    del doc["dataset_identity"], doc["history"]
    (run / "config.json").write_text(json.dumps(doc))
    assert cli_main(["train", str(dataset), "--out", str(run), "--resume", "--steps", "3"]) == 0


# ---------------------------------------------------------------------------------------------------------
# crafted and foreign .pt files


class _Payload:
    """Unpickling this runs ``exec`` of a statement that creates a marker file."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({str(self.marker)!r}, 'w').close()",))


def _craft(path: Path, marker: Path, real: dict) -> None:
    torch.save({**real, "model": _Payload(marker)}, path)


def test_crafted_model_pt_is_refused_and_runs_nothing(capsys, dataset, finished_run, tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    marker = tmp_path / "ran"
    real = torch.load(run / "model.pt", weights_only=True)
    _craft(run / "model.pt", marker, real)
    with pytest.raises(UserError, match="not an s3k model"):
        load_network(run)
    refused(capsys, ["evaluate", str(run), "--data", str(dataset)], str(run / "model.pt"), "not an s3k model",
            "retrain")
    assert not marker.exists()


def test_crafted_checkpoint_is_refused_on_resume_and_runs_nothing(capsys, dataset, finished_run, tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    before = (run / "config.json").read_bytes()
    marker = tmp_path / "ran"
    real = torch.load(run / "checkpoint.pt", weights_only=True)
    _craft(run / "checkpoint.pt", marker, real)
    refused(capsys, ["train", str(dataset), "--out", str(run), "--resume", "--steps", "3"],
            str(run / "checkpoint.pt"), "not an s3k checkpoint")
    assert not marker.exists()
    assert (run / "config.json").read_bytes() == before


def test_foreign_and_truncated_files_are_refused(capsys, dataset, finished_run, tmp_path):
    run = _copy_run(finished_run, tmp_path / "run")
    torch.save({"weights": torch.zeros(2)}, run / "model.pt")  # loads, but is not an s3k model
    with pytest.raises(UserError, match="not an s3k model"):
        load_network(run)
    data = (run / "checkpoint.pt").read_bytes()
    (run / "checkpoint.pt").write_bytes(data[: len(data) // 2])
    # --resume reads the final model first (a finished run is left as it is), then the checkpoint
    refused(capsys, ["train", str(dataset), "--out", str(run), "--resume"], str(run / "model.pt"),
            "not an s3k model")
    (run / "model.pt").unlink()
    refused(capsys, ["train", str(dataset), "--out", str(run), "--resume"], str(run / "checkpoint.pt"))
    with pytest.raises(UserError, match="checkpoint"):
        read_checkpoint_step(run / "checkpoint.pt")


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9, 0.99])
def test_truncated_model_is_one_line_naming_the_file(capsys, dataset, finished_run, tmp_path, fraction):
    run = _copy_run(finished_run, tmp_path / "run")
    data = (run / "model.pt").read_bytes()
    (run / "model.pt").write_bytes(data[: int(len(data) * fraction)])
    refused(capsys, ["evaluate", str(run), "--data", str(dataset)], str(run / "model.pt"), "truncated")


def test_corrupt_image_is_one_line_naming_the_file(capsys, dataset, finished_run, tmp_path):
    import shutil

    data = tmp_path / "ds"
    shutil.copytree(dataset, data, ignore=shutil.ignore_patterns(".cache*"))
    png = sorted((data / "images" / "cam0").glob("*.png"))[0]
    png.write_bytes(png.read_bytes()[:60])
    name = f"images/cam0/{png.name}"
    refused(capsys, ["train", str(data), "--out", str(tmp_path / "run"), *TINY], name, "cannot decode")
    refused(capsys, ["evaluate", str(finished_run), "--data", str(data), "--split", "labelled"], name,
            "cannot decode")


def test_a_train_refused_for_a_corrupt_image_leaves_no_run_behind(capsys, dataset, tmp_path):
    import shutil

    data = tmp_path / "ds"
    shutil.copytree(dataset, data, ignore=shutil.ignore_patterns(".cache*"))
    png = sorted((data / "images" / "cam0").glob("*.png"))[0]
    good = png.read_bytes()
    png.write_bytes(good[:60])
    run = tmp_path / "run"
    refused(capsys, ["train", str(data), "--out", str(run), *TINY], png.name, "cannot decode")
    assert not (run / "config.json").exists()
    png.write_bytes(good)  # fixed: the same command now trains, no --overwrite needed
    shutil.rmtree(data / ".cache", ignore_errors=True)
    assert cli_main(["train", str(data), "--out", str(run), *TINY]) == 0


def test_a_training_that_ends_with_non_finite_weights_exits_non_zero(capsys, dataset, tmp_path, monkeypatch):
    """Weights that overflow in the last step (here made to) leave no model.pt: the command says so and
    fails instead of exiting 0."""
    step = torch.optim.Adam.step

    def overflowing(self, *args, **kwargs):
        out = step(self, *args, **kwargs)
        with torch.no_grad():
            self.param_groups[0]["params"][0].fill_(float("inf"))
        return out

    monkeypatch.setattr(torch.optim.Adam, "step", overflowing)
    run = tmp_path / "run"
    capsys.readouterr()
    assert cli_main(["train", str(dataset), "--out", str(run), *TINY]) == 1
    err = capsys.readouterr().err
    assert "s3k train: error: training stopped" in err and "non-finite" in err and "--lr" in err
    assert not (run / "model.pt").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without a CUDA GPU")
@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_a_device_the_machine_lacks_is_one_line(capsys, dataset, finished_run, tmp_path, command):
    run = tmp_path / "run"
    if command == "train":
        argv = ["train", str(dataset), "--out", str(run), *TINY, "--device", "cuda"]
    else:
        argv = ["evaluate", str(finished_run), "--data", str(dataset), "--device", "cuda"]
    refused(capsys, argv, "--device cuda", "no such CUDA GPU")
    assert not run.exists()


def test_two_pass_options_are_refused_before_the_coarse_pass(dataset, tmp_path):
    from s3k.config import TrainConfig
    from s3k.train import train

    cfg = TrainConfig.from_flat(steps=2, channels=(8, 16), res_blocks=1, two_pass=True)
    for options in ({"crop_size": 0}, {"crop_extent": float("nan")}, {"crop_margin": -1.0},
                    {"coarse_stride": 3}, {"image_size": 64}):
        (name,) = options
        with pytest.raises(UserError, match=name.replace("_", ".")):
            train(dataset, tmp_path / "run", cfg.replace(**options))
        assert not (tmp_path / "run").exists()


def test_resume_refuses_a_preset_that_is_not_the_runs_configuration(capsys, dataset, finished_run, tmp_path):
    """``--preset`` with ``--resume`` was ignored: the run went on with its own configuration. A preset that
    differs from the run's where a resume may not change it is refused, as that field's option is."""
    run = _copy_run(finished_run, tmp_path / "run")
    before = contents(run)
    refused(capsys, ["train", str(dataset), "--out", str(run), "--resume", "--preset", "box-fast"],
            "--preset box-fast", str(run), "drop --preset")
    assert contents(run) == before


def test_resume_takes_the_preset_the_run_was_trained_with(capsys, dataset, tmp_path):
    """A two-pass run started from a preset (its options recorded, more steps since) resumes with
    ``--preset`` of that name, its own steps kept; another preset names the field that differs."""
    from s3k.run_folder import RunFolder
    from s3k.train.presets import preset

    run = RunFolder(tmp_path / "run")
    run.path.mkdir()
    run.write_config(preset("box-fast").replace(steps=7))
    argv = ["train", str(dataset), "--out", str(run.path), "--resume", "--print-config"]
    capsys.readouterr()
    assert cli_main([*argv, "--preset", "box-fast"]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == 7
    refused(capsys, [*argv, "--preset", "box-headline"], "crop_size to 192", "trained with 128")
    assert cli_main([*argv, "--preset", "box-headline", "--crop-size", "128", "--crop-margin", "0.1"]) == 0
