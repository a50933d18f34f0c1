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
