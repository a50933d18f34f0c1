"""The skeleton in s3k's pictures: drawn by :mod:`s3k.base.draw` in ``s3k track --overlay`` and ``s3k evaluate
--report``, recorded in a trained run's meta."""

from __future__ import annotations

import json

import numpy as np
from helpers.synthetic_rig import make_dataset

from s3k.base.draw import draw_overlay, draw_views, edge_indices, keypoint_colours
from s3k.detector import DetectorMeta


def test_edge_indices_name_keypoints_by_index_and_skip_others():
    np.testing.assert_array_equal(edge_indices([("c", "a"), ("a", "paw")], ["a", "b", "c"]), [[2, 0]])
    assert edge_indices([], ["a"]).shape == (0, 2)


def test_overlay_draws_the_skeleton_between_the_reprojected_points():
    image = np.zeros((64, 64, 3), np.uint8)
    reproj = np.array([[10.0, 20.0], [50.0, 20.0], [np.nan, np.nan]])
    uv = np.full((3, 2), np.nan)
    used = np.zeros(3, bool)
    colours = keypoint_colours(3)
    plain = draw_overlay(image, reproj, uv, used, colours)
    drawn = draw_overlay(image, reproj, uv, used, colours, edges=np.array([[0, 1], [1, 2]]))
    assert plain[20, 30].max() == 0 and drawn[20, 30].min() > 200  # white, midway along the edge a-b
    assert (drawn[40:] == 0).all()  # the edge to c (not triangulated) is not drawn


def test_views_draw_the_skeleton_between_the_detections():
    images = np.zeros((2, 32, 32, 3), np.uint8)
    pred = np.array([[[4.0, 4.0], [28.0, 4.0]], [[4.0, 28.0], [4.0, 4.0]]])
    tiles = draw_views(images, None, pred, None, scale=1, edges=np.array([[0, 1]]))
    assert tiles[4, 16].min() > 200 and tiles[16, 32 + 4].min() > 200  # along each view's edge
    assert draw_views(images, None, pred, None, scale=1)[4, 16].max() == 0


def test_a_run_records_its_datasets_skeleton(tmp_path):
    from s3k.config import TrainConfig
    from s3k.train import train

    ds = make_dataset(tmp_path / "ds", size=32, labelled=2, unlabelled=2, test=2)
    meta = json.loads((ds / "s3k.json").read_text())
    (ds / "s3k.json").write_text(json.dumps({**meta, "skeleton": [["a", "b"], ["c", "b"]]}))
    cfg = TrainConfig.from_flat(steps=1, batch_labelled=2, batch_unlabelled=2, channels=(8, 8), res_blocks=1,
                                warmup_steps=0, val_every=0, progress=False, threads=1)
    train(ds, tmp_path / "run", cfg)
    recorded = DetectorMeta.from_dict(json.loads((tmp_path / "run" / "config.json").read_text())["meta"])
    assert recorded.skeleton == [("a", "b"), ("c", "b")]
    # a run trained before the skeleton was recorded takes its dataset's, where that is still there
    older = DetectorMeta.from_dict({**recorded.to_dict(), "skeleton": []})
    assert older.recorded_skeleton() == [("a", "b"), ("c", "b")]
    unknown = DetectorMeta.from_dict({**recorded.to_dict(), "skeleton": [], "geometry": None})
    assert unknown.recorded_skeleton() == []


def test_track_overlay_draws_the_runs_skeleton(tmp_path, monkeypatch):
    from helpers.tiny_detector import save_run
    from helpers.track_rig import CAMERAS, KEYPOINTS, NET_SIZE, VIDEO_SIZE, make_rig

    import s3k.inference.track
    from s3k import cli
    from s3k.data.formats.anipose import write_anipose_calibration
    from s3k.data.video import write_video
    from s3k.model import UNetConfig

    calib = tmp_path / "calibration.toml"
    write_anipose_calibration(calib, make_rig())
    W, H = VIDEO_SIZE
    for name in CAMERAS:
        write_video(tmp_path / f"{name}.mkv", [np.full((H, W, 3), 90, np.uint8)] * 2, fps=25, codec="ffv1")
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=2,
                        sigma=2.0, units="mm", skeleton=[("tail", "nose")],
                        model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())
    run = save_run(tmp_path / "run", meta, seed=0)
    edges, real = [], s3k.inference.track.draw_overlay

    def draw(*args, **kwargs):
        edges.append(args[5])
        return real(*args, **kwargs)

    monkeypatch.setattr(s3k.inference.track, "draw_overlay", draw)  # as the tracker imported it
    assert cli.main(["track", str(run), "--videos", *[f"{c}={tmp_path / c}.mkv" for c in CAMERAS],
                     "--calibration", str(calib), "--out", str(tmp_path / "p.csv"), "--overlay",
                     str(tmp_path / "ov"), "--no-progress"]) == 0
    assert len(edges) == 2 * len(CAMERAS)
    for e in edges:
        np.testing.assert_array_equal(e, [[KEYPOINTS.index("tail"), KEYPOINTS.index("nose")]])
