"""Every command's output goes through one check (``s3k.base.outputs``): a dataset's files, a run's own files
and the call's own inputs are never written over, with or without --overwrite; an existing file needs it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers.tiny_detector import save_run

from s3k import cli
from s3k.base.outputs import RUN_NAMES, check_output, check_output_folder
from s3k.detector import DetectorMeta
from s3k.model import UNetConfig


@pytest.fixture
def files(tmp_path):
    """A dataset folder (its s3k.json and labels), a run with a model, a calibration and a 3D CSV."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "s3k.json").write_text(json.dumps({"format": "s3k-dataset"}))
    (data / "labels.csv").write_text("frame,camera,keypoint,u,v,visible\n")
    meta = DetectorMeta(keypoints=["a"], cameras=["cam0", "cam1"], image_size=(32, 32), stride=2, sigma=2.0,
                        model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())
    run = save_run(tmp_path / "run", meta, seed=0)
    calibration = tmp_path / "calibration.toml"
    calibration.write_text("[cam_0]\nname = 'cam0'\n")
    tracks = tmp_path / "points3d.csv"
    tracks.write_text("a_x,a_y,a_z,a_error,a_ncams,a_score,fnum\n0,0,0,0,2,1,0\n")
    return data, run, calibration, tracks


def _contents(*paths: Path) -> list[bytes]:
    return [p.read_bytes() for p in paths]


def _refused(argv: list[str], capsys, *words: str) -> None:
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, err


@pytest.mark.parametrize("extra", [[], ["--overwrite"]])
def test_export_never_writes_over_a_dataset_file_or_the_run(files, capsys, extra):
    data, run, _, _ = files
    before = _contents(data / "labels.csv", run / "model.pt")
    _refused(["export", str(run), "--format", "onnx", "--out", str(data / "labels.csv"), *extra], capsys,
             str(data / "labels.csv"), "dataset")
    _refused(["export", str(run), "--format", "torchscript", "--out", str(run / "model.pt"), *extra], capsys,
             str(run / "model.pt"), "file of the run")
    assert _contents(data / "labels.csv", run / "model.pt") == before


def test_export_needs_overwrite_for_an_existing_file(files, capsys, tmp_path):
    _, run, _, _ = files
    out = tmp_path / "detector.pt"
    out.write_text("keep me")
    _refused(["export", str(run), "--format", "torchscript", "--out", str(out)], capsys, "--overwrite")
    assert out.read_text() == "keep me"
    assert cli.main(["export", str(run), "--format", "torchscript", "--out", str(out), "--overwrite"]) == 0
    assert out.read_bytes() != b"keep me"


def test_track_never_writes_over_its_inputs(files, capsys, tmp_path):
    _, run, calibration, _ = files
    video = tmp_path / "cam0.mp4"
    video.write_bytes(b"not a video")
    before = _contents(calibration, video)
    _refused(["track", str(run), "--videos", f"cam0={video}", "cam1=other.mp4", "--calibration",
              str(calibration), "--out", str(calibration), "--overwrite"], capsys, "--calibration", "input")
    _refused(["track", str(run), "--videos", f"cam0={video}", "cam1=other.mp4", "--calibration",
              str(calibration), "--out", str(video), "--overwrite"], capsys, "--videos", "input")
    _refused(["track", str(run), "--videos", f"cam0={video}", "cam1=other.mp4", "--calibration",
              str(calibration), "--out", str(run / "config.json"), "--overwrite"], capsys, "file of the run")
    assert _contents(calibration, video) == before


def test_export_tracks_never_writes_over_its_own_csv(files, capsys, tmp_path):
    _, _, calibration, tracks = files
    before = _contents(tracks, calibration)
    _refused(["export-tracks", str(tracks), "--format", "nwb", "--out", str(tracks), "--fps", "30",
              "--overwrite"], capsys, "CSV", "input")
    _refused(["export-tracks", str(tracks), "--format", "nwb", "--out", str(calibration), "--fps", "30",
              "--calibration", str(calibration), "--overwrite"], capsys, "--calibration")
    assert _contents(tracks, calibration) == before


def test_train_never_writes_a_run_into_a_dataset(files, capsys):
    data, _, _, _ = files
    before = sorted(p.name for p in data.iterdir())
    _refused(["train", str(data), "--out", str(data)], capsys, "is the dataset")
    _refused(["train", str(data), "--out", str(data / "run")], capsys, "inside the dataset")
    assert sorted(p.name for p in data.iterdir()) == before


def test_a_link_into_a_dataset_is_refused_as_the_file_itself(files, tmp_path):
    data, _, _, _ = files
    link = tmp_path / "link.csv"
    link.symlink_to(data / "labels.csv")
    with pytest.raises(ValueError, match="dataset"):
        check_output(link, overwrite=True)


def test_new_files_beside_a_run_and_fresh_folders_are_fine(files, tmp_path):
    _, run, _, _ = files
    assert check_output(run / "tracks.csv", overwrite=False) == run / "tracks.csv"
    assert check_output_folder(tmp_path / "report") == tmp_path / "report"


def test_the_run_names_are_those_the_runs_write():
    from s3k import detector
    from s3k.run_folder import RunFolder

    assert set(detector.RUN_FILES) | {detector.TWO_PASS_FILE, RunFolder.ESTIMATES, RunFolder.CPU,
                                      RunFolder.OPTIONS, "coarse", "fine", "crops"} == RUN_NAMES
