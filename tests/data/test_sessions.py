"""A dataset of several recordings (sessions): each frame's session, each session's rig and metadata, and
datasets without sessions read as one."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.synthetic_rig import make_dataset, make_sessions_dataset, rig

from s3k.data import Dataset, DatasetError, check_dataset


def test_sessions_with_their_own_rigs_are_read_per_session(tmp_path):
    path = make_sessions_dataset(tmp_path / "ds", {"day1": 0.0, "day2": 0.4})
    meta = json.loads((path / "s3k.json").read_text())
    assert meta["calibration"] == "per_session"
    assert sorted(p.name for p in (path / "calibration").iterdir()) == ["day1.json", "day2.json"]
    ds = Dataset.open(path)
    assert ds.sessions == ["day1", "day2"]
    assert ds.session_info("day2") == {"frame_rate": 30.0, "subject": "dots-1"}
    ids = ds.frames()
    assert ds.session_of(ids).tolist() == ["day1"] * 10 + ["day2"] * 10
    assert len(ds.frames("test", session="day2")) == 3
    assert set(ds.session_of(ds.frames("labelled", session="day1"))) == {"day1"}
    cams = ds.calibration(ids, np.float64).numpy()
    for name, turn in (("day1", 0.0), ("day2", 0.4)):
        K, _, R, t = rig(32, turn)
        rows = ds.session_of(ids) == name
        np.testing.assert_array_equal(cams["R"][rows], np.broadcast_to(R, (10, 4, 3, 3)))
        np.testing.assert_array_equal(cams["t"][rows], np.broadcast_to(t, (10, 4, 3)))
        np.testing.assert_array_equal(ds.rig(np.float64, session=name).numpy()["K"], K)
    assert not np.allclose(cams["R"][0], cams["R"][-1])  # the cameras moved between the days
    assert ds.frame_times(ds.frames(session="day2")).tolist() == list(range(10))
    assert ds.summary()["sessions"]["day2"] == {"labelled": 3, "unlabelled": 4, "test": 3}
    with pytest.raises(ValueError, match="per session"):
        ds.rig()


def test_a_dataset_without_sessions_is_one_session(tmp_path):
    ds = Dataset.open(make_dataset(tmp_path / "ds", labelled=2, unlabelled=2, test=1))
    assert ds.sessions == ["default"]
    assert set(ds.session_of(ds.frames())) == {"default"}
    assert ds.session_info("default") == {}
    assert ds.static_calibration and ds.rig().shape == (4,)
    assert ds.frame_times(ds.frames()).tolist() == ds.frames().tolist()


def test_sessions_sharing_one_rig_keep_a_static_calibration(tmp_path):
    path = make_sessions_dataset(tmp_path / "ds", {"a": 0.2, "b": 0.2})
    ds = Dataset.open(path)
    assert ds.static_calibration and ds.sessions == ["a", "b"]
    assert (path / "calibration.json").is_file() and not (path / "calibration").exists()


def test_a_missing_session_rig_or_bad_session_metadata_is_named(tmp_path):
    path = make_sessions_dataset(tmp_path / "ds", {"day1": 0.0, "day2": 0.4})
    (path / "calibration" / "day2.json").unlink()
    with pytest.raises(DatasetError, match=r"calibration/day2.json: file missing .*per_session"):
        Dataset.open(path)
    path = make_sessions_dataset(tmp_path / "ds2", {"day1": 0.0, "day2": 0.4})
    meta = json.loads((path / "s3k.json").read_text())
    meta["sessions"]["day2"]["frame_rate"] = -3
    meta["sessions"]["day3"] = {}
    (path / "s3k.json").write_text(json.dumps(meta))
    problems, _ = check_dataset(path, check_images=False)
    text = [str(p) for p in problems]
    assert any("sessions.day2.frame_rate" in t and "positive number" in t for t in text)
    assert any("sessions.day3" in t and "no frame" in t for t in text)
    frames = (path / "frames.csv").read_text().replace(",day1,", ",day 1,", 1)
    (path / "frames.csv").write_text(frames)
    problems, _ = check_dataset(path, check_images=False)
    assert any("field 'session'" in str(p) and "'day 1'" in str(p) for p in problems)


def test_each_session_reads_its_own_videos(tmp_path):
    import shutil

    from s3k.data.video import write_video

    path = make_sessions_dataset(tmp_path / "ds", {"day1": 0.0, "day2": 0.4}, labelled=2, unlabelled=1,
                                 test=1)
    ds = Dataset.open(path, cache="none")
    expected = ds.images(ds.frames())
    meta = json.loads((path / "s3k.json").read_text())
    videos: dict[str, dict[str, str]] = {}
    for name in ds.sessions:
        images = ds.images(ds.frames(session=name))  # in video_frame order
        for c, cam in enumerate(ds.cameras):
            rel = f"videos/{name}/{cam}.mkv"
            (path / rel).parent.mkdir(parents=True, exist_ok=True)
            write_video(path / rel, list(images[:, c]), fps=30, codec="ffv1")
            videos.setdefault(name, {})[cam] = rel
    meta["images"] = {"type": "video", "sessions": videos}
    (path / "s3k.json").write_text(json.dumps(meta))
    shutil.rmtree(path / "images")
    again = Dataset.open(path, cache="none")
    np.testing.assert_array_equal(again.images(again.frames()), expected)
    del meta["images"]["sessions"]["day2"]
    (path / "s3k.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="images.sessions.day2.*no videos given"):
        Dataset.open(path)


def _per_frame_dataset(path, turn):
    from helpers.synthetic_rig import CAMERAS, KEYPOINTS, _add_frame

    from s3k.data import DatasetWriter

    rng = np.random.default_rng(5)
    with DatasetWriter(path, KEYPOINTS, CAMERAS, (32, 32), "m", per_frame_calibration=True) as w:
        for f, split in enumerate(["labelled", "labelled", "unlabelled", "test"]):
            _add_frame(w, f, split, rig(32, turn), 32, rng, calibration=True, label_test=True)
    return path


@pytest.mark.parametrize("kind", ["same rig", "other rig", "per session", "per frame"])
def test_a_dataset_added_as_a_session_keeps_every_frame_with_its_rig(tmp_path, kind, capsys):
    from s3k.cli import main

    into = {"same rig": lambda p: make_dataset(p, labelled=2, unlabelled=2, test=1),
            "other rig": lambda p: make_dataset(p, labelled=2, unlabelled=2, test=1),
            "per session": lambda p: make_sessions_dataset(p, {"a": 0.0, "b": 0.3}),
            "per frame": lambda p: _per_frame_dataset(p, 0.1)}[kind](tmp_path / "into")
    part = make_dataset(tmp_path / "part", labelled=2, unlabelled=3, test=2, seed=7)
    if kind != "same rig":  # the cameras moved: the part's rig turned
        meta = json.loads((part / "calibration.json").read_text())
        K, dist, R, t = rig(32, 0.7)
        for c, cam in enumerate(meta["cameras"]):
            meta["cameras"][cam].update(R=R[c].tolist(), t=t[c].tolist())
        (part / "calibration.json").write_text(json.dumps(meta))
    old, new = Dataset.open(into, cache="none"), Dataset.open(part, cache="none")
    old_images, new_images = old.images(old.frames()), new.images(new.frames())
    old_cams, new_cams = (d.calibration(d.frames(), np.float64).numpy() for d in (old, new))
    assert main(["import", "--into", str(into), "--session", "late", "--dataset", str(part),
                 "--subject", "dots"]) == 0
    ds = Dataset.open(into, cache="none")
    mode = json.loads((into / "s3k.json").read_text())["calibration"]
    assert mode == {"same rig": "static", "other rig": "per_session", "per session": "per_session",
                    "per frame": "per_frame"}[kind]
    assert ds.sessions == [*old.sessions, "late"] and ds.session_info("late")["subject"] == "dots"
    added = ds.frames(session="late")
    assert added.tolist() == list(range(old.frame_ids.max() + 1, old.frame_ids.max() + 8))
    np.testing.assert_array_equal(ds.images(old.frames()), old_images)
    np.testing.assert_array_equal(ds.images(added), new_images)
    for ids, cams in ((old.frames(), old_cams), (added, new_cams)):
        got = ds.calibration(ids, np.float64).numpy()
        for f in ("K", "R", "t"):
            np.testing.assert_array_equal(got[f], cams[f])
    np.testing.assert_array_equal(ds.labels(added)[0], new.labels(new.frames())[0])
    np.testing.assert_array_equal(ds.points3d(added)[0], new.points3d(new.frames())[0])
    assert ds.split_of(added).tolist() == new.split_of(new.frames()).tolist()
    assert (part / "s3k.json").is_file()  # the added dataset is left as it was


def test_a_held_out_session_is_test_frames_only(tmp_path, capsys):
    from s3k.cli import main

    into = make_dataset(tmp_path / "into", labelled=2, unlabelled=2, test=1)
    part = make_dataset(tmp_path / "part", labelled=2, unlabelled=3, test=2, seed=7)
    assert main(["import", "--into", str(into), "--session", "held", "--dataset", str(part),
                 "--test-sessions", "held"]) == 0
    ds = Dataset.open(into)
    assert ds.summary()["sessions"]["held"] == {"labelled": 0, "unlabelled": 0, "test": 4}
    assert main(["import", "--into", str(into), "--session", "held", "--dataset", str(part)]) != 0
    err = capsys.readouterr().err.strip()
    assert "already holds session 'held'" in err and len(err.splitlines()) == 1
