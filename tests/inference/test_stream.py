"""``s3k stream``: live 3D keypoints from synchronized sources, one JSON line per frame
(:mod:`s3k.inference.stream`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers.rig_inputs import rig_inputs
from helpers.track_rig import (
    CAMERAS,
    FRAMES,
    KEYPOINTS,
    NET_SIZE,
    VIDEO_SIZE,
    OracleDetector,
    make_rig,
    moving_points,
)

from s3k import cli
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.video import write_video
from s3k.detector import DetectorMeta, OnePassDetector
from s3k.geometry import project
from s3k.inference.stream import Source, stream
from s3k.model import UNetConfig


@pytest.fixture()
def rig_videos(tmp_path):
    """Lossless videos whose frames are one grey level each (the oracle reads them back), their calibration,
    the true points and an oracle network whose heatmaps peak at their projections."""
    rig = make_rig()
    calib = tmp_path / "calibration.toml"
    write_anipose_calibration(calib, rig)
    W, H = VIDEO_SIZE
    videos = {}
    for c, name in enumerate(CAMERAS):
        videos[name] = tmp_path / f"{name}.mkv"
        write_video(videos[name], [np.full((H, W, 3), 20 + 10 * f + 3 * c, np.uint8) for f in range(FRAMES)],
                    fps=25, codec="ffv1")
    inputs, cams = rig_inputs(videos, rig, NET_SIZE, "pad")
    X = torch.as_tensor(moving_points(FRAMES))  # (F, K, 3) mm
    uv, _ = project(cams, X[:, None])
    M = torch.as_tensor(np.stack([c.M for c in inputs]))
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), stride=2).to_dict(), units="mm")
    oracle = OracleDetector(uv @ M[:, :2, :2].transpose(-1, -2) + M[:, None, :2, 2], 2, 2.0)
    return {"calibration": calib, "videos": videos, "X": X.numpy(), "oracle": oracle, "meta": meta,
            "cams": cams, "boxes": np.stack([c.box for c in inputs])}


def test_stream_prints_a_line_per_frame_with_the_true_points(rig_videos, monkeypatch, capsys):
    import s3k.detector.detector

    v = rig_videos
    monkeypatch.setattr(s3k.detector.detector, "load_network", lambda *a, **k: (v["oracle"], v["meta"]))
    args = ["stream", "run", "--calibration", str(v["calibration"]), "--sources",
            *[f"{c}={v['videos'][c]}" for c in CAMERAS]]
    assert cli.main(args) == 0
    captured = capsys.readouterr()
    lines = [json.loads(line) for line in captured.out.splitlines()]
    assert [line["frame"] for line in lines] == list(range(FRAMES))  # one line per frame, in order
    for line in lines:
        got = np.array([line["points"][k] for k in KEYPOINTS])
        np.testing.assert_allclose(got, v["X"][line["frame"]], rtol=0, atol=1e-3)  # mm, at 1 m
        assert all(line["valid"].values()) and line["latency_ms"] >= 0 and line["time"] >= 0
    times = [line["time"] for line in lines]
    assert times == sorted(times)
    assert f"{FRAMES} frames in" in captured.err and "frames/s" in captured.err
    assert "the sources run at 25 frames/s" in captured.err
    # a bad source is one line naming it
    assert cli.main(["stream", "run", "--calibration", str(v["calibration"]), "--sources",
                     f"left={v['videos']['left']}", "top=missing.mkv"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "missing.mkv" in err


def test_stream_filter_is_causal_and_keeps_the_raw_points(rig_videos, monkeypatch, capsys):
    import s3k.detector.detector

    v = rig_videos
    monkeypatch.setattr(s3k.detector.detector, "load_network", lambda *a, **k: (v["oracle"], v["meta"]))
    args = ["stream", "run", "--calibration", str(v["calibration"]), "--filter", "kalman",
            "--sources", *[f"{c}={v['videos'][c]}" for c in CAMERAS]]
    assert cli.main(args) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["frame"] for line in lines] == list(range(FRAMES))
    for line in lines:
        raw = np.array([line["raw"][k] for k in KEYPOINTS])
        np.testing.assert_allclose(raw, v["X"][line["frame"]], rtol=0, atol=1e-3)
        assert all(line["valid"].values()) and line["rejected"] == []
    # the first frame has nothing before it: the filter starts at the measurement
    assert lines[0]["points"] == lines[0]["raw"]
    # the same frames cut short give the same lines: no frame depends on one after it
    assert cli.main([*args, "--max-frames", "3"]) == 0
    short = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [s["points"] for s in short] == [line["points"] for line in lines[:3]]


class _Interrupting(Source):
    """A source that gives ``n`` frames of one grey level per frame, then is interrupted (Ctrl-C)."""

    def __init__(self, camera: int, n: int) -> None:
        self.spec, self.size, self.fps, self.live = f"fake{camera}", VIDEO_SIZE, 0.0, False
        self.camera, self.n, self.i, self.closed = camera, n, 0, False

    def read(self):
        if self.i == self.n:
            raise KeyboardInterrupt
        W, H = VIDEO_SIZE
        frame = np.full((H, W, 3), 20 + 10 * self.i + 3 * self.camera, np.uint8)
        self.i += 1
        return frame

    def close(self) -> None:
        self.closed = True


def test_ctrl_c_stops_the_stream_between_frames_and_closes_the_sources(rig_videos):
    import io

    v = rig_videos
    detector = OnePassDetector(v["oracle"], v["meta"])
    sources = {name: _Interrupting(c, 2) for c, name in enumerate(CAMERAS)}
    out = io.StringIO()
    summary = stream(detector, sources, v["cams"], v["boxes"], out)
    assert summary.interrupted and summary.frames == 2
    assert [json.loads(line)["frame"] for line in out.getvalue().splitlines()] == [0, 1]
    assert all(s.closed for s in sources.values())


def test_stream_logs_to_a_rerun_recording(rig_videos, monkeypatch, tmp_path, capsys):
    pytest.importorskip("rerun")
    import s3k.detector.detector

    v = rig_videos
    monkeypatch.setattr(s3k.detector.detector, "load_network", lambda *a, **k: (v["oracle"], v["meta"]))
    rrd = tmp_path / "stream.rrd"
    assert cli.main(["stream", "run", "--calibration", str(v["calibration"]), "--max-frames", "2", "--rerun",
                     str(rrd), "--sources", *[f"{c}={v['videos'][c]}" for c in CAMERAS]]) == 0
    captured = capsys.readouterr()
    assert len(captured.out.splitlines()) == 2
    from s3k.inference.rerun_log import recording_summary

    summary = recording_summary(rrd)  # read back with Rerun's own reader
    assert summary["frames"] == [0, 1] and f"wrote {rrd}: 2 frames" in captured.err
    for cam in CAMERAS:  # each camera's frustum and compressed view, its detections and reprojections
        for entity in ("", "/image", "/detections", "/reprojections"):
            assert f"/world/cameras/{cam}{entity}" in summary["entities"]
        assert "EncodedImage:blob" in summary["entities"][f"/world/cameras/{cam}/image"]
    assert {"/world/keypoints", "/world/skeleton", "/confidence/nose"} <= set(summary["entities"])
    # it opens on the layout of 's3k view': the views in a grid, the 3D view, one plot of confidence
    from helpers.rerun_layout import file_views

    views = file_views(rrd)
    origins = sorted(v["origin"] for v in views if v["kind"] == "2D")
    assert origins == sorted(f"/world/cameras/{c}" for c in CAMERAS)
    assert sorted(v["kind"] for v in views if v["kind"] != "2D") == ["3D", "TimeSeries"]


def test_ctrl_c_in_the_logger_counts_every_line_written(rig_videos):
    """Ctrl-C while the 5th frame is logged (its line already written): the summary counts 5 frames."""
    import io

    v = rig_videos
    detector = OnePassDetector(v["oracle"], v["meta"])
    sources = {name: _Interrupting(c, 9) for c, name in enumerate(CAMERAS)}
    out = io.StringIO()

    def log(i, views, det):
        if i == 4:
            raise KeyboardInterrupt

    summary = stream(detector, sources, v["cams"], v["boxes"], out, log=log)
    assert summary.interrupted
    assert len(out.getvalue().splitlines()) == 5 and summary.frames == 5


def test_image_folders_have_no_frame_rate_unless_given(rig_videos, monkeypatch, capsys, tmp_path):
    """Image folders record no frame rate: the summary says it is unknown, and ``--fps`` gives it."""
    import cv2

    import s3k.detector.detector
    from s3k.data import video

    v = rig_videos
    monkeypatch.setattr(s3k.detector.detector, "load_network", lambda *a, **k: (v["oracle"], v["meta"]))
    folders = {}
    for name in CAMERAS:
        folders[name] = tmp_path / f"{name}-frames"
        folders[name].mkdir()
        for i, frame in video.iter_frames(v["videos"][name]):
            cv2.imwrite(str(folders[name] / f"img{i:03d}.png"), frame[..., ::-1])
    args = ["stream", "run", "--calibration", str(v["calibration"]), "--sources",
            *[f"{c}={folders[c]}" for c in CAMERAS]]
    assert cli.main(args) == 0
    err = capsys.readouterr().err
    assert f"{FRAMES} frames in" in err and "frames/s" in err and "30 frames/s" not in err
    assert f"the frame rate of {', '.join(CAMERAS)} is unknown (--fps gives it)" in err
    assert cli.main([*args, "--fps", "12.5"]) == 0
    assert "the sources run at 12.5 frames/s" in capsys.readouterr().err
