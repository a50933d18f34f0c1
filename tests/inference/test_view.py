"""``s3k view`` and ``s3k stream --rerun``: recordings saved to .rrd files (never a display) and read back
with Rerun's own reader (``rerun.chunk.RrdReader``): their entities, frames, the logged numbers and the
size per frame."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.paths import REPO
from helpers.real_recording import REAL, needs_real
from helpers.rerun_layout import blueprint_views, file_views
from helpers.synthetic_rig import make_dataset
from helpers.tiny_detector import save_run
from helpers.track_rig import CAMERAS, FRAMES, KEYPOINTS, VIDEO_SIZE, make_rig, moving_points

from s3k import cli
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.tracks_csv import csv_header, write_source
from s3k.data.video import write_video
from s3k.detector import DetectorMeta
from s3k.geometry import project
from s3k.model import UNetConfig

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from s3k.geometry.framing import DEFAULT_FOV_Y, camera_centres, frame  # noqa: E402
from s3k.inference.rerun_log import layout, recording_summary  # noqa: E402


def _column(path: Path, entity: str, component: str) -> dict[int, list]:
    """``{frame: value}`` of one component of an entity in a .rrd file (``-1`` for a static value)."""
    out: dict[int, list] = {}
    for chunk in RrdReader(str(path)).stream():
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names:
            continue
        frames = batch.column("frame").to_pylist() if "frame" in batch.schema.names else [-1] * batch.num_rows
        for f, v in zip(frames, batch.column(component).to_pylist()):
            out[int(f)] = v
    return out


def _camera_entities(cam: str, *children: str) -> set[str]:
    return {f"/world/cameras/{cam}", *(f"/world/cameras/{cam}/{c}" for c in children)}


# ------------------------------------------------------------------------------------------------------------
# Tracks


@pytest.fixture()
def tracks(tmp_path):
    """A 3D CSV of the moving dots as 's3k track' writes it (nose's point missing in frame 2), its
    calibration named beside it, the videos and a DeepLabCut config.yaml holding a skeleton."""
    rig = make_rig()
    calib = tmp_path / "calibration.toml"
    write_anipose_calibration(calib, rig)
    X = moving_points(FRAMES)
    X[2, 0] = np.nan
    path = tmp_path / "points3d.csv"
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(csv_header(KEYPOINTS))
        for i in range(FRAMES):
            row = []
            for k in range(len(KEYPOINTS)):
                row += [*(f"{v:.8g}" for v in X[i, k]), "0.5", "3", f"{0.1 * (k + 1) + 0.01 * i:.6f}"]
            writer.writerow(row + [str(i)])
    write_source(path, "mm", calibration=calib)
    W, H = VIDEO_SIZE
    videos = {}
    for c, name in enumerate(CAMERAS):
        videos[name] = tmp_path / f"{name}.mkv"
        write_video(videos[name], [np.full((H, W, 3), 40 + 20 * c, np.uint8)] * FRAMES, fps=25, codec="ffv1")
    config = tmp_path / "config.yaml"
    config.write_text("bodyparts: [nose, ear, tail]\nskeleton:\n- [nose, ear]\n- [ear, tail]\n")
    return {"csv": path, "rig": rig, "X": X, "videos": videos, "skeleton": config}


def test_view_tracks_logs_cameras_images_points_skeleton_confidence_reprojections(tracks, tmp_path, capsys):
    rrd = tmp_path / "tracks.rrd"
    argv = ["view", str(tracks["csv"]), "--videos", *[f"{c}={p}" for c, p in tracks["videos"].items()],
            "--skeleton", str(tracks["skeleton"]), "--image-scale", "0.5", "--save", str(rrd)]
    assert cli.main(argv) == 0
    assert f"wrote {rrd}: {FRAMES} frames" in capsys.readouterr().out
    summary = recording_summary(rrd)
    entities = set(summary["entities"])
    for cam in CAMERAS:
        assert _camera_entities(cam, "image", "reprojections") <= entities
        components = summary["entities"][f"/world/cameras/{cam}"]
        assert {"Pinhole:image_from_camera", "Transform3D:mat3x3"} <= set(components)
        images = summary["entities"][f"/world/cameras/{cam}/image"]
        assert images == ["EncodedImage:blob", "EncodedImage:media_type"]
    assert {"/world/keypoints", "/world/skeleton", *(f"/confidence/{k}" for k in KEYPOINTS)} <= entities
    assert summary["frames"] == list(range(FRAMES))

    rig = tracks["rig"]
    arrays = rig.cameras.numpy()
    # the camera: OpenCV's world -> camera transform, its intrinsics scaled to the half-size image and moved
    # by Rerun's half-pixel (pixel centres at 0.5)
    M = np.array([[0.5, 0, 0.25], [0, 0.5, 0.25], [0, 0, 1]])
    pinhole = _column(rrd, "/world/cameras/top", "Pinhole:image_from_camera")[-1]
    np.testing.assert_allclose(np.array(pinhole).reshape(3, 3).T, M @ arrays["K"][1], rtol=1e-6)
    rotation = _column(rrd, "/world/cameras/top", "Transform3D:mat3x3")[-1]
    np.testing.assert_allclose(np.array(rotation).reshape(3, 3).T, arrays["R"][1], atol=1e-6)
    # the reprojections: the points projected with the lens distortion, in the logged image's pixels
    uv, _ = project(rig.cameras.to(torch.float64), torch.as_tensor(np.nan_to_num(tracks["X"][3])))
    logged = np.array(_column(rrd, "/world/cameras/top/reprojections", "Points2D:positions")[3])
    np.testing.assert_allclose(logged, uv[1].numpy() @ M[:2, :2].T + M[:2, 2], atol=1e-3)
    # the skeleton: an edge where both ends are triangulated (frame 2 has no nose: one edge)
    strips = _column(rrd, "/world/skeleton", "LineStrips3D:strips")
    assert len(strips[3]) == 2 and len(strips[2]) == 1
    np.testing.assert_allclose(strips[3][0], tracks["X"][3][[0, 1]], rtol=1e-6)
    assert len(_column(rrd, "/world/keypoints", "Points3D:positions")[2]) == 2
    # each keypoint's confidence is the CSV's score
    np.testing.assert_allclose(_column(rrd, "/confidence/tail", "Scalars:scalars")[4], [0.34], rtol=1e-6)


def _matrix(rrd: Path, entity: str) -> np.ndarray:
    return np.array(_column(rrd, entity, "Transform3D:mat3x3")[-1]).reshape(3, 3).T  # stored by columns


def test_view_opens_on_the_cameras_beside_a_3d_view_framed_on_the_work(tracks, tmp_path):
    rrd = tmp_path / "layout.rrd"
    argv = ["view", str(tracks["csv"]), "--videos", *[f"{c}={p}" for c, p in tracks["videos"].items()],
            "--save", str(rrd)]
    assert cli.main(argv) == 0
    views = file_views(rrd)
    kinds = [v["kind"] for v in views]
    assert len(views) == len(CAMERAS) + 2 and kinds.count("3D") == 1 and kinds.count("TimeSeries") == 1
    # one 2D view per camera, on its image and 2D points
    origins = sorted(v["origin"] for v in views if v["kind"] == "2D")
    assert origins == sorted(f"/world/cameras/{c}" for c in CAMERAS)
    assert all(v["query"] == ["$origin/**"] for v in views if v["kind"] == "2D")
    # one plot holds every keypoint's confidence, each series named as its keypoint
    series = next(v for v in views if v["kind"] == "TimeSeries")
    logged = [e for e in recording_summary(rrd)["entities"] if e.startswith("/confidence/")]
    assert sorted(logged) == sorted(f"/confidence/{k}" for k in KEYPOINTS)
    assert series["query"] == ["$origin/**"] and all(e.startswith(series["origin"] + "/") for e in logged)
    assert {_column(rrd, f"/confidence/{k}", "SeriesLines:names")[-1][0] for k in KEYPOINTS} == set(KEYPOINTS)
    # the 3D view: the world placed under the root with the table's normal along the root's +Z (this rig's
    # table is the world's z = 0) and the points' centre at the origin; its eye sees every point
    assert _column(rrd, "/", "ViewCoordinates:xyz")[-1] == rr.ViewCoordinates.RIGHT_HAND_Z_UP.as_arrow_array(
    ).to_pylist()
    M = _matrix(rrd, "/world")
    T = np.array(_column(rrd, "/world", "Transform3D:translation")[-1])
    X = tracks["X"].reshape(-1, 3)
    X = X[np.isfinite(X).all(-1)]
    display = X @ M.T + T
    np.testing.assert_allclose(np.median(X, axis=0) @ M.T + T, 0, atol=1e-3)
    assert np.degrees(np.arccos(M[2] @ [0, 0, 1])) < 15
    arrays = tracks["rig"].cameras.numpy()
    assert (camera_centres(arrays["R"], arrays["t"]) @ M.T + T)[:, 2].min() > display[:, 2].max()
    (view3d,) = [v for v in views if v["kind"] == "3D"]
    assert view3d["origin"] == "/" and view3d["query"] == ["/world/**"]
    eye = np.array(view3d["eye"]["position"])
    assert view3d["eye"]["look_target"] == [0, 0, 0] and view3d["eye"]["eye_up"] == [0, 0, 1] and eye[2] > 0
    sight = (display - eye) @ -eye / np.linalg.norm(display - eye, axis=-1) / np.linalg.norm(eye)
    assert (sight >= np.cos(np.radians(DEFAULT_FOV_Y / 2))).all()
    # the names are drawn once: beside the 3D keypoints, not on every view's points
    assert _column(rrd, "/world/keypoints", "Points3D:show_labels")[3] == [True]
    assert _column(rrd, "/world/cameras/top/reprojections", "Points2D:show_labels")[3] == [False]


def test_the_layout_object_has_a_2d_view_per_camera_one_3d_view_and_one_plot_of_confidence():
    arrays = make_rig().cameras.numpy()
    framing = frame(arrays["R"], arrays["t"], moving_points(4))
    views = blueprint_views(layout(["a", "b", "c"], framing))
    assert [v.class_identifier for v in views] == ["2D", "2D", "2D", "3D", "TimeSeries"]
    assert [str(v.origin) for v in views[:3]] == ["/world/cameras/a", "/world/cameras/b", "/world/cameras/c"]
    assert str(views[4].origin) == "/confidence"
    # a dataset logs no confidence: no plot
    assert [v.class_identifier for v in blueprint_views(layout(["a"], framing, confidence=False))] == [
        "2D", "3D"]


def test_view_tracks_without_videos_shows_cameras_and_points(tracks, tmp_path):
    rrd = tmp_path / "bare.rrd"
    assert cli.main(["view", str(tracks["csv"]), "--start", "2", "--step", "2", "--save", str(rrd)]) == 0
    summary = recording_summary(rrd)
    assert summary["frames"] == [2, 4] and "/world/cameras/left/image" not in summary["entities"]
    assert {"/world/cameras/left", "/world/cameras/left/reprojections", "/world/keypoints"} <= set(
        summary["entities"])


def test_view_refuses_what_it_cannot_show(tracks, tmp_path, capsys):
    assert cli.main(["view", str(tracks["csv"]), "--split", "test", "--save", str(tmp_path / "x.rrd")]) == 1
    assert "--split is for a dataset or a run" in capsys.readouterr().err
    assert cli.main(["view", str(tracks["csv"]), "--videos", f"front={tracks['videos']['top']}",
                     "--save", str(tmp_path / "x.rrd")]) == 1
    assert "camera 'front' is not in" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("skeleton:\n- [nose, paw]\n")
    argv = ["view", str(tracks["csv"]), "--skeleton", str(bad), "--save", str(tmp_path / "x.rrd")]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert "names 'paw', which is not a keypoint" in err and len(err.strip().splitlines()) <= 2
    (tmp_path / "there.rrd").write_text("mine")
    assert cli.main(["view", str(tracks["csv"]), "--save", str(tmp_path / "there.rrd")]) == 1
    assert (tmp_path / "there.rrd").read_text() == "mine"
    short = {c: tmp_path / f"short-{c}.mkv" for c in CAMERAS}
    for path in short.values():
        write_video(path, [np.zeros((VIDEO_SIZE[1], VIDEO_SIZE[0], 3), np.uint8)] * 3, fps=25, codec="ffv1")
    assert cli.main(["view", str(tracks["csv"]), "--videos", *[f"{c}={p}" for c, p in short.items()],
                     "--save", str(tmp_path / "there.rrd"), "--overwrite"]) == 1
    assert f"frame {FRAMES - 1} is beyond the 3 frames of --videos" in capsys.readouterr().err
    # a recording that fails on the way leaves the file it was to replace as it was
    from s3k.inference.rerun_log import RerunLog

    with pytest.raises(RuntimeError), RerunLog("s3k view", tmp_path / "there.rrd", KEYPOINTS, CAMERAS):
        raise RuntimeError("failed on the way")
    assert (tmp_path / "there.rrd").read_text() == "mine" and not list(tmp_path.glob("*.partial"))


# ------------------------------------------------------------------------------------------------------------
# A dataset, and a run's detections on one


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = make_dataset(tmp_path_factory.mktemp("view") / "ds", size=32, labelled=2, unlabelled=2, test=3)
    meta = json.loads((path / "s3k.json").read_text())
    (path / "s3k.json").write_text(json.dumps({**meta, "skeleton": [["a", "b"], ["b", "c"]]}))
    return path


def test_view_dataset_logs_labels_and_ground_truth(dataset, tmp_path):
    rrd = tmp_path / "ds.rrd"
    assert cli.main(["view", str(dataset), "--save", str(rrd), "--image-scale", "1"]) == 0
    summary = recording_summary(rrd)
    for cam in ("cam0", "cam3"):
        assert _camera_entities(cam, "image", "labels", "reprojections") <= set(summary["entities"])
    assert summary["frames"] == list(range(7))
    strips = _column(rrd, "/world/skeleton", "LineStrips3D:strips")
    assert all(len(s) == 2 for s in strips.values()) and len(strips) == 7  # every frame's truth is complete
    labels = _column(rrd, "/world/cameras/cam0/labels", "Points2D:positions")
    assert len(labels[0]) == 3 and len(labels[5]) == 0  # labelled frame 0; test frames show no labels
    assert cli.main(["view", str(dataset), "--split", "test", "--save", str(tmp_path / "t.rrd")]) == 0
    assert recording_summary(tmp_path / "t.rrd")["frames"] == [4, 5, 6]


def test_view_run_logs_detections_beside_the_truth(dataset, tmp_path):
    meta = DetectorMeta(keypoints=["a", "b", "c"], cameras=["cam0", "cam1", "cam2", "cam3"],
                        image_size=(32, 32), stride=2, sigma=2.0, skeleton=[("a", "c")],
                        model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())
    run = save_run(tmp_path / "run", meta, seed=0, dataset=str(dataset), head_std=0.5)
    rrd = tmp_path / "run.rrd"
    assert cli.main(["view", str(run), "--data", str(dataset), "--save", str(rrd), "--no-images"]) == 0
    summary = recording_summary(rrd)
    assert summary["frames"] == [4, 5, 6]  # the test split
    entities = set(summary["entities"])
    assert _camera_entities("cam1", "detections", "reprojections", "labels") <= entities
    assert "/world/cameras/cam1/image" not in entities
    world = {"/world/keypoints", "/world/skeleton", "/world/truth", "/world/truth_skeleton"}
    assert world | {"/confidence/b"} <= entities
    truth = _column(rrd, "/world/truth_skeleton", "LineStrips3D:strips")
    assert all(len(s) == 1 for s in truth.values())  # the run's skeleton (a-c), not the dataset's
    radii = _column(rrd, "/world/cameras/cam1/detections", "Points2D:radii")[5]
    assert len(radii) and all(1.5 <= r <= 4.5 for r in radii)  # radius by confidence weight


# ------------------------------------------------------------------------------------------------------------
# The real recording


def _real_run(path: Path) -> Path:
    """An untrained tiny detector with the real recording's keypoints and the skeleton of its SLEAP files."""
    import sleap_io as sio

    skeleton = sio.load_slp(str(REAL / "back" / "minimal_back_proofread.slp"), open_videos=False).skeletons[0]
    meta = DetectorMeta(keypoints=list(skeleton.node_names), cameras=["back", "mid", "side", "top"],
                        image_size=(64, 52), stride=2, sigma=2.0, units="mm",
                        model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict(),
                        skeleton=list(skeleton.edge_names))
    return save_run(path, meta, seed=0, head_std=0.5)


REAL_VIDEOS = [f"{c}={REAL / c / f'minimal_{c}.mp4'}" for c in ("back", "mid", "side", "top")]


@needs_real
def test_view_opens_the_real_recordings_tracks_with_cameras_images_and_skeleton(tmp_path):
    pytest.importorskip("sleap_io")
    rrd = tmp_path / "real.rrd"
    argv = ["view", str(REPO / "docs/results/real/tracked-s3k.csv"),
            "--calibration", str(REAL / "calibration.toml"), "--videos", *REAL_VIDEOS,
            "--skeleton", str(REAL / "back" / "minimal_back_proofread.slp"), "--max-frames", "4",
            "--image-scale", "1", "--save", str(rrd)]
    assert cli.main(argv) == 0
    summary = recording_summary(rrd)
    for cam in ("back", "mid", "side", "top"):
        assert _camera_entities(cam, "image", "reprojections") <= set(summary["entities"])
    assert summary["frames"] == [0, 1, 2, 3]
    strips = _column(rrd, "/world/skeleton", "LineStrips3D:strips")
    assert [len(s) for s in strips.values()] == [14] * 4  # every edge of the mouse's skeleton
    assert summary["bytes_per_frame"] < 1e6  # four 1280x1024 views
    # the reprojections sit on the mouse: within a few pixels of the proofread labels in the cameras whose
    # shipped calibration is right (side's copies top's: about 92 px off, the recording's README says)
    from s3k.data.formats.sleap import read_sleap_analysis

    for cam, most in (("mid", 10.0), ("top", 10.0), ("side", None)):
        labels = read_sleap_analysis(REAL / cam / f"minimal_{cam}_proofread.analysis.h5")
        positions = _column(rrd, f"/world/cameras/{cam}/reprojections", "Points2D:positions")
        names = _column(rrd, f"/world/cameras/{cam}/reprojections", "Points2D:labels")
        # full size: Rerun's pixels are s3k's moved by half a pixel
        off = [np.linalg.norm(np.array(uv) - 0.5 - labels.uv[f, labels.keypoints.index(k)])
               for f in range(4) for k, uv in zip(names[f], positions[f])]
        median = float(np.nanmedian(off))
        assert (median < most) if most else (median > 50), (cam, median)


@needs_real
def test_stream_rerun_of_the_real_recording_is_under_a_megabyte_a_frame(tmp_path, capsys):
    pytest.importorskip("sleap_io")
    run = _real_run(tmp_path / "run")
    for scale in ("0.5", "1"):
        rrd = tmp_path / f"stream-{scale}.rrd"
        assert cli.main(["stream", str(run), "--calibration", str(REAL / "calibration.toml"),
                         "--max-frames", "3", "--rerun", str(rrd), "--image-scale", scale,
                         "--sources", *REAL_VIDEOS]) == 0
        summary = recording_summary(rrd)
        assert summary["frames"] == [0, 1, 2]
        assert {"/world/cameras/side/image", "/world/cameras/side/detections", "/world/skeleton"} <= set(
            summary["entities"])
        assert summary["bytes_per_frame"] < 1e6, summary["bytes_per_frame"]
    assert f"wrote {rrd}" in capsys.readouterr().err
