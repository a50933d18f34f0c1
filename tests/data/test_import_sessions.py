"""``s3k import --into DATASET --session NAME`` and ``--manifest``: recordings of other days added to one
dataset as sessions, each with its own rig, and the refusals that leave the dataset as it was."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers.recordings import CAMS, import_argv, write_recording

from s3k.cli import main
from s3k.data import Dataset
from s3k.geometry import project


@pytest.fixture(scope="module")
def days(tmp_path_factory):
    root = tmp_path_factory.mktemp("days")
    return {"day1": write_recording(root / "day1", turn=0.0, seed=1),
            "day2": write_recording(root / "day2", turn=0.5, seed=2, n_frames=10)}


def _snapshot(folder):
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in files}


def _first(days, tmp_path):
    out = tmp_path / "ds"
    assert main(import_argv(days["day1"], "--labelled", "4", "--test", "3", "--session", "day1",
                            "--subject", "mouse-1", "--out", str(out))) == 0
    return out


def test_a_session_added_keeps_its_rig_labels_and_frames(days, tmp_path, capsys):
    out = _first(days, tmp_path)
    assert main(import_argv(days["day2"], "--labelled", "3", "--test", "2", "--into", str(out),
                            "--session", "day2")) == 0
    assert "added session day2" in capsys.readouterr().out
    ds = Dataset.open(out)
    assert ds.sessions == ["day1", "day2"]
    assert json.loads((out / "s3k.json").read_text())["calibration"] == "per_session"
    assert ds.session_info("day1")["subject"] == "mouse-1"
    assert ds.session_info("day2")["frame_rate"] == 25.0
    assert ds.session_info("day2")["source"]["calibration"].endswith("day2/calibration.toml")
    one, two = ds.frames(session="day1"), ds.frames(session="day2")
    assert one.tolist() == list(range(12)) and two.tolist() == list(range(12, 22))  # ids continue
    assert ds.frame_times(two).tolist() == list(range(10))
    assert len(ds.frames("labelled", session="day2")) == 3 and len(ds.frames("test", session="day2")) == 2
    for name, ids in (("day1", one), ("day2", two)):
        rec = days[name]
        lab = np.concatenate([ds.frames("labelled", session=name), ds.frames("test", session=name)])
        uv, mask = ds.labels(lab)
        assert mask.all()
        # every label is its own session's 3D point seen through its own session's cameras
        X = torch.as_tensor(rec["X"][ds.frame_times(lab)][:, None], dtype=torch.float64)
        reproj = project(ds.calibration(lab, np.float64), X)[0].numpy()
        np.testing.assert_allclose(uv, reproj, atol=1e-3)
        f = int(ids[5])
        for c, cam in enumerate(ds.cameras):
            np.testing.assert_array_equal(ds.images([f])[0, c], rec["frames"][cam][5])


def test_refusals_leave_the_dataset_as_it_was(days, tmp_path, capsys):
    out = _first(days, tmp_path)
    before = _snapshot(out)
    cases = [
        (["--into", str(out), "--session", "day1"], "already holds session 'day1'"),
        (["--into", str(out)], "--session NAME"),
        (["--into", str(out), "--session", "day2", "--keypoints", "head,body"], "keypoints"),
        # a box of another shape than the dataset's images would be stretched to them
        (["--into", str(out), "--session", "day2", "--crop", "0,0,20,20"], "would be stretched"),
    ]
    for extra, expected in cases:
        assert main(import_argv(days["day2"], *extra)) != 0
        err = capsys.readouterr().err.strip()
        assert expected in err and len(err.splitlines()) == 1, err
    assert main(import_argv(days["day2"], "--into", str(out), "--session", "day2",
                            cameras=CAMS[:2])) != 0
    err = capsys.readouterr().err.strip()
    assert "cameras" in err and len(err.splitlines()) == 1, err
    assert _snapshot(out) == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["ds"]  # nothing left beside it


def test_a_manifest_imports_every_session(days, tmp_path, capsys):
    manifest = tmp_path / "sessions.toml"
    lines = []
    for name, turn_test in (("day1", 3), ("day2", 2)):
        root = days[name]["root"]
        lines += ["[[sessions]]", f'session = "{name}"', f'calibration = "{root}/calibration.toml"',
                  f"test = {turn_test}", "labelled = 3", f'subject = "animal-{name}"', "[sessions.videos]",
                  *(f'{cam} = "{root}/{cam}.mkv"' for cam in CAMS), "[sessions.dlc]",
                  *(f'{cam} = "{root}/CollectedData_{cam}.csv"' for cam in CAMS)]
    manifest.write_text("\n".join(lines) + "\n")
    assert main(["import", "--manifest", str(manifest), "--out", str(tmp_path / "ds")]) == 0
    ds = Dataset.open(tmp_path / "ds")
    assert ds.sessions == ["day1", "day2"]
    assert [len(ds.frames("test", session=s)) for s in ds.sessions] == [3, 2]
    assert ds.session_info("day2")["subject"] == "animal-day2"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"sessions": [{"session": "x", "videos": {}}]}))
    assert main(["import", "--manifest", str(bad), "--out", str(tmp_path / "other")]) != 0
    err = capsys.readouterr().err.strip()
    assert "sessions[0] has no field 'calibration'" in err and len(err.splitlines()) == 1


def test_held_out_blocks_keep_labelled_frames_away(tmp_path, capsys):
    from s3k.data.splits import held_out_split

    candidates = np.arange(0, 200)
    for seed in range(5):
        splits = held_out_split(candidates, candidates, 10, 30, seed, 1, margin=15, blocks=2)
        test = np.array([f for f, s in splits.items() if s == "test"])
        labelled = np.array([f for f, s in splits.items() if s == "labelled"])
        assert len(test) == 30 and len(labelled) == 10
        assert np.abs(labelled[:, None] - test[None, :]).min() > 15
        assert (np.diff(test) > 1).sum() <= 1  # two contiguous runs at most
    with pytest.raises(ValueError, match=r"--labelled 10: only \d+ frames with labels lie more than 15"):
        held_out_split(np.arange(40), np.arange(40), 10, 20, 0, 1, margin=15)


def test_held_out_last_frames_follow_every_labelled_frame():
    from s3k.data.splits import held_out_split

    candidates = np.arange(3, 120, 2)  # frames with labels: every other frame, not from 0
    for margin in (0, 7):
        splits = held_out_split(candidates, np.arange(120), 10, 20, 1, 1, margin=margin, last=True)
        test = np.array([f for f, s in splits.items() if s == "test"])
        labelled = np.array([f for f, s in splits.items() if s == "labelled"])
        assert list(test) == list(candidates[-20:])
        assert len(labelled) == 10 and labelled.max() < test.min() - margin
        assert {s for f, s in splits.items() if f < test.min() and f not in labelled} == {"unlabelled"}


def test_import_holds_out_blocks_or_whole_sessions(days, tmp_path, capsys):
    long = write_recording(tmp_path / "long", n_frames=60, seed=3)
    out = tmp_path / "blocks"
    assert main(import_argv(long, "--labelled", "8", "--test", "10", "--margin", "6", "--out", str(out))) == 0
    ds = Dataset.open(out)
    test, lab = ds.frames("test"), ds.frames("labelled")
    assert len(test) == 10 and np.all(np.diff(np.sort(test)) == 1)  # one contiguous block
    assert np.abs(lab[:, None] - test[None, :]).min() > 6
    out = tmp_path / "held"
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"sessions": [
        {"session": name, "calibration": str(days[name]["root"] / "calibration.toml"), "labelled": 3,
         "test": 2, "videos": {cam: str(days[name]["root"] / f"{cam}.mkv") for cam in CAMS},
         "dlc": {cam: str(days[name]["root"] / f"CollectedData_{cam}.csv") for cam in CAMS}}
        for name in ("day1", "day2")]}))
    assert main(["import", "--manifest", str(manifest), "--test-sessions", "day2", "--out", str(out)]) == 0
    ds = Dataset.open(out)
    assert ds.summary()["sessions"]["day2"] == {"labelled": 0, "unlabelled": 0, "test": 10}
    assert ds.summary()["sessions"]["day1"]["labelled"] == 3
    # a training's validation frames (on which its confidence is calibrated) keep out of the held-out session
    from s3k.config import TrainConfig
    from s3k.train.run_setup import frames_used

    used = frames_used(ds, TrainConfig())
    assert len(used) and set(ds.session_of(used)) == {"day1"}
    assert set(ds.frames("test", session="day1")) <= set(used)
    capsys.readouterr()
    assert main(["import", "--manifest", str(manifest), "--test-sessions", "day3", "--out",
                 str(tmp_path / "x")]) != 0
    err = capsys.readouterr().err.strip()
    assert "'day3' is not a session" in err and len(err.splitlines()) == 1
