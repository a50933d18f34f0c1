"""`s3k add-frames`: the frames a track was most in doubt about, added to a dataset from the videos and queued
first for labelling (s3k.label.queue)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from helpers.files import contents
from helpers.track_rig import CAMERAS, KEYPOINTS, run_track

from s3k import cli
from s3k.data import Dataset, DatasetWriter
from s3k.data.video import iter_frames
from s3k.inference.track_filter import DOUBT_COLUMNS
from s3k.label.queue import read_queue


def _dataset(track_recording, path):
    """Frames 0 (labelled), 1 (test) and 2 (unlabelled) of the recording's videos, ids 0-2, video_frame."""
    rig = track_recording["rig"]
    views = {c: dict(iter_frames(track_recording["videos"][c], [0, 1, 2])) for c in CAMERAS}
    with DatasetWriter(path, KEYPOINTS, CAMERAS, tuple(int(v) for v in rig.size[0]), units="mm",
                       calibration=rig.cameras) as w:
        uv = np.full((len(CAMERAS), len(KEYPOINTS), 2), 20.0)
        for f, split in enumerate(["labelled", "test", "unlabelled"]):
            images = np.stack([views[c][f] for c in CAMERAS])
            w.add_frame(f, split, images, labels=uv if split != "unlabelled" else None,
                        extra={"video_frame": f})
    return path


def _rank(path, fnums):
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(DOUBT_COLUMNS)
        for rank, f in enumerate(fnums, 1):
            out.writerow([rank, f, 10.0 - rank, 0.5, 1.0, 2.0, 0, 0, KEYPOINTS[0], ""])


def test_add_frames_adds_the_worst_new_frames_from_the_videos_and_queues_them_first(track_recording, tmp_path,
                                                                                    capsys):
    data = _dataset(track_recording, tmp_path / "data")
    tracks = tmp_path / "points3d.csv"
    assert run_track(track_recording, tracks, "--min-weight", "0") == 0
    _rank(tmp_path / "points3d.doubt.csv", [1, 0, 4, 3, 2, 5])  # a test frame and a labelled one first
    assert cli.main(["add-frames", str(tracks), "--data", str(data), "--worst", "2", "--spacing", "0"]) == 0
    assert "already test" in capsys.readouterr().out
    ds = Dataset.open(data, cache="none")
    assert ds.frames().tolist() == [0, 1, 2, 3, 4]
    assert ds.column("video_frame").astype(int).tolist() == [0, 1, 2, 4, 3]  # the worse one first
    assert ds.split_of(np.array([3, 4])).tolist() == ["unlabelled", "unlabelled"]
    # the new frames' views are the videos' frames (the dataset's images are whole frames)
    images = ds.images([3, 4])
    for c, cam in enumerate(CAMERAS):
        video = dict(iter_frames(track_recording["videos"][cam], [3, 4]))
        assert np.array_equal(images[0, c], video[4]) and np.array_equal(images[1, c], video[3])
    queue = read_queue(data)
    assert [(int(r["frame"]), int(r["video_frame"]), int(r["rank"])) for r in queue] == [(3, 4, 1), (4, 3, 2)]
    # a frame the dataset holds is queued without a copy, first; the earlier queue follows
    _rank(tmp_path / "points3d.doubt.csv", [2, 4])
    assert cli.main(["add-frames", str(tracks), "--data", str(data), "--worst", "1"]) == 0
    assert Dataset.open(data, cache="none").frames().tolist() == [0, 1, 2, 3, 4]
    assert [int(r["frame"]) for r in read_queue(data)] == [2, 3, 4]


def test_add_frames_refuses_when_nothing_can_be_queued(track_recording, tmp_path, capsys):
    data = _dataset(track_recording, tmp_path / "data")
    tracks = tmp_path / "points3d.csv"
    assert run_track(track_recording, tracks, "--min-weight", "0", "--filter", "none") == 0
    _rank(tmp_path / "points3d.doubt.csv", [0, 1])
    capsys.readouterr()
    assert cli.main(["add-frames", str(tracks), "--data", str(data), "--worst", "3"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(data) in err and not (data / "label-queue.csv").exists()


def _refused(capsys, argv, *needles):
    capsys.readouterr()
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


@pytest.mark.parametrize("column, value", [("fnum", "x"), ("fnum", "-3"), ("fnum", "2.5"), ("fnum", ""),
                                           ("rank", "abc"), ("rank", "-1"), ("doubt", "high"),
                                           ("doubt", "nan")])
def test_a_ranking_whose_frame_rank_or_doubt_is_no_number_is_refused_in_one_line(track_recording, tmp_path,
                                                                                  capsys, column, value):
    data = _dataset(track_recording, tmp_path / "data")
    tracks = tmp_path / "points3d.csv"
    assert run_track(track_recording, tracks, "--min-weight", "0", "--filter", "none") == 0
    ranking = tmp_path / "points3d.doubt.csv"
    _rank(ranking, [4, 3])
    rows = list(csv.DictReader(open(ranking, newline="")))
    rows[1][column] = value
    with open(ranking, "w", newline="") as fh:
        writer = csv.DictWriter(fh, DOUBT_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    before = contents(data)
    _refused(capsys, ["add-frames", str(tracks), "--data", str(data), "--worst", "2"], str(ranking), "line 3",
             column, repr(value))
    assert contents(data) == before


@pytest.mark.parametrize("named", ["../points3d.doubt.csv", "/etc/passwd", "sub/points3d.doubt.csv", ".."])
def test_a_record_naming_a_ranking_outside_its_folder_is_refused_in_one_line(track_recording, tmp_path,
                                                                              capsys, named):
    data = _dataset(track_recording, tmp_path / "data")
    tracks = tmp_path / "t" / "points3d.csv"
    tracks.parent.mkdir()
    assert run_track(track_recording, tracks, "--min-weight", "0", "--filter", "none") == 0
    _rank(tmp_path / "points3d.doubt.csv", [4, 3])
    sidecar = tmp_path / "t" / "points3d.csv.s3k.json"
    record = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps({**record, "doubt": named}))
    before = contents(data)
    _refused(capsys, ["add-frames", str(tracks), "--data", str(data), "--worst", "2"], str(sidecar),
             "'doubt'", repr(named), "broken")
    assert contents(data) == before


@pytest.mark.parametrize("text, needle", [("{not json", "not JSON"), ("[1, 2]", "a JSON list"),
                                          ('{"units": 3}', "'units' is 3"),
                                          ('{"units": "mm", "videos": ["a.mp4"]}', "'videos'"),
                                          ('{"units": "mm", "videos": {"left": 1}}', "'videos'"),
                                          ('{"units": "mm", "fps": true}', "'fps'")])
def test_a_broken_record_is_reported_as_broken_not_as_missing(track_recording, tmp_path, capsys, text,
                                                              needle):
    """add-frames, export-tracks and view read the record beside a CSV: a broken one is named, with what is
    wrong in it, where before it was taken for no record at all."""
    data = _dataset(track_recording, tmp_path / "data")
    tracks = tmp_path / "points3d.csv"
    assert run_track(track_recording, tracks, "--min-weight", "0", "--filter", "none") == 0
    sidecar = tmp_path / "points3d.csv.s3k.json"
    sidecar.write_text(text)
    for argv in (["add-frames", str(tracks), "--data", str(data), "--worst", "2"],
                 ["export-tracks", str(tracks), "--format", "nwb", "--out", str(tmp_path / "t.nwb")]):
        err = _refused(capsys, argv, str(sidecar), "broken", needle)
        assert "no " not in err.split("broken")[0]
    assert not (tmp_path / "t.nwb").exists()
