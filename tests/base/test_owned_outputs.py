"""One rule for every command that writes: a new path, a folder s3k made for the same kind of output, or (with
--overwrite) s3k's own output; never a dataset's folder except by the commands that make datasets, and never
a file s3k did not write (the message names one)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from helpers.tiny_detector import save_run

from s3k import cli
from s3k.detector import DetectorMeta
from s3k.model import UNetConfig

SIM = ["--size", "32", "--labelled", "1", "--unlabelled", "0", "--test", "0", "--workers", "1",
       "--no-progress"]


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(argv: list[str], capsys, *words: str) -> str:
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, err
    return err


def _hidden(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


@pytest.fixture
def dataset(tmp_path) -> Path:
    data = tmp_path / "data" / "box"
    data.mkdir(parents=True)
    (data / "s3k.json").write_text(json.dumps({"format": "s3k-dataset"}))
    (data / "labels.csv").write_text("frame,camera,keypoint,u,v,visible\n")
    return data


@pytest.fixture
def user(tmp_path) -> Path:
    """A folder of someone's own files."""
    folder = tmp_path / "user"
    folder.mkdir()
    for name in ("notes.txt", "README.md", "metrics.json", "back.mp4", "config.json", "train.log"):
        (folder / name).write_text(f"my own {name}\n")
    return folder


def _meta(size=(40, 32)) -> DetectorMeta:
    return DetectorMeta(keypoints=["a", "b", "c"], cameras=["back", "mid", "side", "top"], image_size=size,
                        stride=2, sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())


# ------------------------------------------------------------------------------------------ robot grasp
def test_grasp_never_replaces_a_file_without_overwrite_nor_writes_into_a_dataset(user, dataset, capsys,
                                                                                  monkeypatch):
    import s3k.robot.grasp

    def no_trials(*args, **kwargs):
        raise AssertionError("the trials ran before the output was checked")

    monkeypatch.setattr(s3k.robot.grasp, "run_trials", no_trials)
    before = _tree(user)
    grasp = ["robot", "grasp", "--ground-truth", "--trials", "1", "--out"]
    _refused([*grasp, str(user / "notes.txt")], capsys, str(user / "notes.txt"), "exists", "--overwrite")
    _refused([*grasp, str(dataset / "grasp.json")], capsys, "dataset")
    _refused([*grasp, str(dataset / "grasp.json"), "--overwrite"], capsys, "dataset")
    assert _tree(user) == before and sorted(p.name for p in dataset.iterdir()) == ["labels.csv", "s3k.json"]


# ---------------------------------------------------------------------------------- experiment --publish
@pytest.fixture
def summarized(tmp_path) -> Path:
    from helpers.experiment_results import fake_result, old_summary

    import s3k.experiments as ex

    results = [fake_result({"labelled": L, "unlabelled": U, "seed": s}, v)
               for (L, U), vs in {(3, 0): [10, 11], (3, 9): [2, 3], (10, 0): [5, 6], (10, 9): [5, 7]}.items()
               for s, v in enumerate(vs)]
    exp = tmp_path / "exp" / "label-efficiency"
    exp.mkdir(parents=True)
    (exp / "summary.json").write_text(json.dumps(old_summary(ex.aggregate(results, {}))))
    return tmp_path / "exp"


def test_publish_refuses_a_folder_of_other_files_and_a_dataset(summarized, user, dataset, capsys):
    argv = ["experiment", "label-efficiency", "--out", str(summarized), "--summarize-only", "--publish"]
    before = _tree(user)
    _refused([*argv, str(user)], capsys, str(user), "s3k did not write", "README.md")
    _refused([*argv, str(dataset)], capsys, "is the dataset")
    _refused([*argv, str(summarized / "label-efficiency")], capsys, "input")
    assert _tree(user) == before and sorted(p.name for p in dataset.iterdir()) == ["labels.csv", "s3k.json"]
    # a new folder, then the same published folder again, are fine
    pub = summarized / "published"
    assert cli.main([*argv, str(pub)]) == 0
    assert cli.main([*argv, str(pub)]) == 0
    assert {"summary.json", "README.md"} <= {p.name for p in pub.iterdir()}
    # another experiment's published folder is not this one's
    _refused(["experiment", "alpha", "--out", str(summarized), "--summarize-only", "--publish", str(pub)],
             capsys)


# ----------------------------------------------------------------------------------------- train --out
def test_train_never_clears_a_folder_that_holds_no_run(user, dataset, capsys):
    before = _tree(user)
    err = _refused(["train", str(dataset), "--out", str(user), "--overwrite"], capsys, str(user), "no run",
                   "config.json")
    assert "already holds a run" not in err
    err = _refused(["train", str(dataset), "--out", str(user)], capsys, "no run")
    assert "already holds a run" not in err
    _refused(["train", str(dataset), "--out", str(user), "--resume"], capsys, "config.json")
    assert _tree(user) == before


def test_two_pass_overwrite_never_deletes_a_file_beside_the_run(tmp_path, dataset, capsys):
    from s3k.detector import CropRule, write_two_pass

    run = tmp_path / "run2p"
    save_run(run / "coarse", _meta(), seed=0)
    save_run(run / "fine", _meta((32, 32)), seed=1)
    write_two_pass(run, CropRule(0.2, 32, 0.0), 40, ["a", "b", "c"])
    (run / "tracks.csv").write_text("my tracks\n")
    before = _tree(run)
    _refused(["train", str(dataset), "--out", str(run), "--two-pass"], capsys, "already holds a run")
    _refused(["train", str(dataset), "--out", str(run), "--two-pass", "--overwrite"], capsys, "tracks.csv",
             "--overwrite would delete it")
    assert _tree(run) == before


# ---------------------------------------------------------------------------------- evaluate, demo, track
def test_evaluate_report_never_writes_into_a_folder_of_other_files(tmp_path, user, dataset, capsys):
    run = save_run(tmp_path / "run", _meta(), seed=0)
    before = _tree(user)
    _refused(["evaluate", str(run), "--data", str(dataset), "--ignore-geometry", "--report", str(user)],
             capsys, str(user), "metrics.json", "s3k did not write")
    assert _tree(user) == before


def test_demo_never_writes_into_a_folder_of_other_files(user, capsys, monkeypatch):
    import s3k.experiments.demo as demo

    def no_rendering(*args, **kwargs):
        raise AssertionError("the demo started before its folder was checked")

    monkeypatch.setattr(demo, "_data", no_rendering)
    before = _tree(user)
    _refused(["demo", "--quick", "--out", str(user), "--no-progress"], capsys, str(user), "s3k did not write")
    assert _tree(user) == before


def test_an_earlier_demo_folder_is_continued(tmp_path):
    from s3k.base.outputs import check_folder
    from s3k.experiments.demo import DEMO_NAMES, is_demo_folder

    folder = tmp_path / "s3k-demo"
    (folder / "pool").mkdir(parents=True)
    (folder / "pool" / "s3k.json").write_text("{}")
    (folder / "report").mkdir()
    assert check_folder(folder, "demo", owns=is_demo_folder, ours=DEMO_NAMES) == folder
    (folder / "thesis.txt").write_text("mine")
    with pytest.raises(ValueError, match="thesis.txt"):
        check_folder(folder, "demo", owns=is_demo_folder, ours=DEMO_NAMES)


def test_track_overlay_never_replaces_a_file_in_a_folder_s3k_did_not_make(tmp_path, user, capsys):
    run = save_run(tmp_path / "run", _meta(), seed=0)
    calibration = tmp_path / "calibration.toml"
    calibration.write_text("[cam_0]\nname = 'back'\n")
    before = _tree(user)
    videos = [f"{c}={tmp_path / c}.mp4" for c in ("back", "mid", "side", "top")]
    _refused(["track", str(run), "--videos", *videos, "--calibration", str(calibration), "--out",
              str(tmp_path / "points3d.csv"), "--overlay", str(user), "--overwrite"], capsys, str(user),
             "s3k did not write", "back.mp4")
    assert _tree(user) == before


# ---------------------------------------------------------------------------------------------- export
def test_two_pass_export_never_replaces_a_companion_file_s3k_did_not_write(tmp_path, capsys):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from s3k.detector import CropRule, write_two_pass

    run = tmp_path / "run2p"
    save_run(run / "coarse", _meta(), seed=0)
    save_run(run / "fine", _meta((32, 32)), seed=1)
    write_two_pass(run, CropRule(0.2, 32, 0.0), 40, ["a", "b", "c"])
    out = tmp_path / "user" / "det.onnx"
    out.parent.mkdir()
    (out.parent / "det.json").write_text('{"mine": true}\n')
    argv = ["export", str(run), "--format", "onnx", "--out", str(out)]
    _refused(argv, capsys, str(out.parent / "det.json"), "exists")
    _refused([*argv, "--overwrite"], capsys, str(out.parent / "det.json"), "not s3k's")
    assert (out.parent / "det.json").read_text() == '{"mine": true}\n'
    assert sorted(p.name for p in out.parent.iterdir()) == ["det.json"]
    # s3k's own export beside it is replaced with --overwrite
    (out.parent / "det.json").unlink()
    assert cli.main(argv) == 0
    assert cli.main([*argv, "--overwrite"]) == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["det.coarse.onnx", "det.fine.onnx", "det.json"]


def test_an_export_that_fails_its_check_leaves_nothing(tmp_path, capsys, monkeypatch):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from helpers.onnx_files import corrupt_exports
    from helpers.tiny_detector import make_run

    run = make_run(tmp_path / "run")
    corrupt_exports(monkeypatch)
    out = tmp_path / "out" / "d.onnx"
    assert cli.main(["export", str(run), "--format", "onnx", "--out", str(out)]) == 1
    assert "nothing was written" in capsys.readouterr().err
    assert list(out.parent.iterdir()) == []


# -------------------------------------------------------------------------------------------- simulate
def _simulated(path: Path) -> Path:
    assert cli.main(["simulate", "box", "--out", str(path), *SIM]) == 0
    return path


def test_simulate_overwrite_never_deletes_a_file_put_in_the_dataset(tmp_path, capsys):
    data = _simulated(tmp_path / "ds")
    (data / "my-notes.txt").write_text("mine\n")
    before = _tree(data)
    capsys.readouterr()
    _refused(["simulate", "box", "--out", str(data), "--overwrite", *SIM], capsys, "my-notes.txt",
             "--overwrite would delete it")
    assert _tree(data) == before
    (data / "my-notes.txt").unlink()
    (data / "images" / "cam0" / "why.txt").write_text("mine too\n")
    _refused(["simulate", "box", "--out", str(data), "--overwrite", *SIM], capsys, "why.txt")
    assert (data / "images" / "cam0" / "why.txt").is_file() and _hidden(tmp_path) == []


def test_simulate_overwrite_through_a_link_keeps_the_link(tmp_path, capsys):
    data = _simulated(tmp_path / "real" / "ds")
    (tmp_path / "links").mkdir()
    link = tmp_path / "links" / "ds"
    link.symlink_to(data, target_is_directory=True)
    stamp = (data / "s3k.json").stat().st_mtime_ns
    assert cli.main(["simulate", "box", "--out", str(link), "--overwrite", *SIM]) == 0
    assert link.is_symlink() and Path(os.readlink(link)) == data
    assert (data / "s3k.json").is_file() and (data / "s3k.json").stat().st_mtime_ns != stamp
    assert _hidden(tmp_path / "links") == [] and _hidden(tmp_path / "real") == []


# -------------------------------------------------------------------------------- impossible requests
def test_simulate_refuses_frames_no_disk_can_hold_before_planning_them(tmp_path, capsys, monkeypatch):
    """Where the memory available is unknown (or large), the disk still bounds the frames."""
    import s3k.sim.generate as generate

    def no_plan(*args, **kwargs):
        raise AssertionError("the frames were planned before the request was refused")

    monkeypatch.setattr(generate, "available_memory", lambda: None)
    monkeypatch.setattr(generate, "frame_plan", no_plan)
    out = tmp_path / "big"
    _refused(["simulate", "box", "--out", str(out), "--test", "1000000000", "--workers", "1",
              "--no-progress"], capsys, "--test 1000000000", "disk")
    assert not out.exists() and _hidden(tmp_path) == []


def test_experiment_refuses_a_size_no_run_can_fit_before_the_sweep(tmp_path, capsys):
    out = tmp_path / "exp"
    _refused(["experiment", "alpha", "--out", str(out), "--scale", "toy", "--size", "100000", "--no-progress",
              "--workers", "1"], capsys, "--size 100000", "every run would fail")
    assert not out.exists()


def test_the_dataset_names_are_those_the_datasets_hold():
    from s3k.base.outputs import DATASET_NAMES, UNFINISHED_MARKER
    from s3k.data import sessions, tables
    from s3k.label import store

    assert {tables.METADATA_FILE, tables.FRAMES_FILE, tables.STATIC_CALIBRATION_FILE,
            tables.PER_FRAME_CALIBRATION_FILE, tables.LABELS_FILE, tables.POINTS3D_FILE, tables.CACHE_DIR,
            sessions.SESSION_CALIBRATION_DIR, store.HISTORY_FILE, store.LOCK_FILE,
            UNFINISHED_MARKER} == DATASET_NAMES


def test_the_run_neighbours_are_those_s3k_keeps_in_a_run_folder():
    from s3k.base.outputs import RUN_NEIGHBOURS
    from s3k.experiments import grid, runner
    from s3k.run_folder import RunFolder

    names = {runner.LOCK_FILE, grid.RESULT_FILE, RunFolder.CPU, RunFolder.OPTIONS}
    assert names == RUN_NEIGHBOURS


def test_the_dataset_writer_never_deletes_a_file_put_in_the_dataset(tmp_path):
    """``s3k robot simulate-insertion --overwrite`` and every other writer of a dataset in place."""
    from s3k.data import DatasetWriter

    data = _simulated(tmp_path / "ds")
    (data / "my-notes.txt").write_text("mine\n")
    with pytest.raises(ValueError, match="my-notes.txt"):
        DatasetWriter(data, ["a"], ["cam0", "cam1"], (16, 16), overwrite=True)
    assert (data / "my-notes.txt").read_text() == "mine\n" and (data / "s3k.json").is_file()


def test_stream_never_replaces_a_recording_without_overwrite(tmp_path, capsys):
    rrd = tmp_path / "stream.rrd"
    rrd.write_bytes(b"an earlier recording")
    _refused(["stream", str(tmp_path / "run"), "--calibration", str(tmp_path / "calibration.toml"), "--rerun",
              str(rrd), "--sources", "a=0", "b=1"], capsys, str(rrd), "--overwrite")
    assert rrd.read_bytes() == b"an earlier recording"


def test_experiment_workspace_and_agent_runs_are_never_inside_a_dataset(dataset, user, tmp_path, capsys):
    before = sorted(p.name for p in dataset.iterdir())
    _refused(["experiment", "alpha", "--out", str(dataset), "--scale", "toy", "--no-progress"], capsys,
             "inside the dataset")
    _refused(["robot", "train-agent", "--out", str(dataset / "agent")], capsys, "inside the dataset")
    assert sorted(p.name for p in dataset.iterdir()) == before
    # an experiment's folder of someone's files is not swept into
    (user / "alpha").mkdir()
    (user / "alpha" / "README.md").write_text("my alpha notes\n")
    _refused(["experiment", "alpha", "--out", str(user), "--scale", "toy", "--no-progress"], capsys,
             "README.md", "s3k did not write")
    assert (user / "alpha" / "README.md").read_text() == "my alpha notes\n"


def test_an_earlier_report_is_written_again_and_a_folder_of_metrics_not(tmp_path, user):
    from s3k.base.outputs import check_folder
    from s3k.cli.evaluate import _earlier_report

    report = tmp_path / "rep"
    report.mkdir()
    (report / "metrics.json").write_text(json.dumps({"rms_px": 1.0, "n_frames": 3}))
    (report / "errors_hist.png").write_bytes(b"png")
    assert check_folder(report, "report", owns=_earlier_report) == report
    (report / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="metrics.json"):
        check_folder(report, "report", owns=_earlier_report, writes={"metrics.json"})
    with pytest.raises(ValueError, match="metrics.json"):
        check_folder(user, "report", owns=_earlier_report, writes={"metrics.json"})


def test_simulate_insertion_never_writes_inside_a_dataset(dataset, capsys):
    pytest.importorskip("gymnasium")
    before = sorted(p.name for p in dataset.iterdir())
    _refused(["robot", "simulate-insertion", "--out", str(dataset / "insertion"), "--size", "16",
              "--labelled", "1", "--unlabelled", "0", "--test", "0", "--no-progress"], capsys,
             "inside the dataset")
    assert sorted(p.name for p in dataset.iterdir()) == before
