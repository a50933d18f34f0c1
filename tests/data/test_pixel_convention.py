"""One pixel convention at every format boundary (:mod:`s3k.data.formats.pixels`): 3D points projected by a
known camera, written in each format's own convention (by the format's own library where it is installed:
sleap-io, pynwb with ndx-pose; otherwise by its published layout), read back by s3k, land within 0.05 px of
s3k's projection; a calibration TOML read by s3k projects where OpenCV projects with the file's numbers; and
``s3k import --label-pixels / --calibration-pixels`` declare files of the other convention."""

from __future__ import annotations

import json
import pickle
from datetime import datetime, timezone

import cv2
import numpy as np
import pytest
import torch
from helpers.recordings import CAMS, KEYPOINTS, write_sleap

from s3k.data.formats import pixels
from s3k.data.formats.anipose import read_anipose_calibration
from s3k.data.formats.deepfly3d import read_deepfly3d_pose
from s3k.data.formats.dlc import find_lightning_pose_csvs, read_dlc_csv
from s3k.data.formats.pose_json import read_mmpose_json, read_openpose_folder
from s3k.data.formats.sleap import read_sleap_analysis
from s3k.geometry import Cameras, project

W, H = 640, 480
TOL = 0.05  # px
NODES = ["nose", "ear", "tail"]
K = np.array([[810.0, 0.0, 318.7], [0.0, 805.0, 243.2], [0.0, 0.0, 1.0]])
DIST = np.array([-0.21, 0.08, 0.001, -0.0005, 0.0])
RVEC = np.array([0.3, -0.5, 0.1])
T = np.array([12.0, -30.0, 900.0])
# 4 frames of 3 points in front of the camera (mm)
X = np.random.default_rng(0).uniform(-120, 120, (4, len(NODES), 3))


def camera() -> Cameras:
    return Cameras.from_numpy(K[None], DIST[None], RVEC[None], T[None], dtype=torch.float64)


def s3k_uv() -> np.ndarray:
    """``(F, K, 2)`` s3k's projection of ``X``: the reference every read-back is held to."""
    return project(camera()[0], torch.as_tensor(X.reshape(-1, 3)))[0].numpy().reshape(X.shape[:2] + (2,))


def corner(uv: np.ndarray) -> np.ndarray:
    """The same points with (0, 0) at the image's top-left corner (OpenPose's, COLMAP's)."""
    return uv + 0.5


def _close(table, uv=None):
    uv = s3k_uv() if uv is None else uv
    assert table.keypoints == NODES
    np.testing.assert_array_equal(table.frame_ids, np.arange(len(uv)))
    assert np.abs(table.uv - uv).max() < TOL


def test_opencv_projects_as_s3k():
    """OpenCV's projection of the camera (the reference of every calibration format) is s3k's."""
    cv, _ = cv2.projectPoints(X.reshape(-1, 3), RVEC, T, K, DIST)
    assert np.abs(cv.reshape(s3k_uv().shape) - s3k_uv()).max() < 1e-6


# ------------------------------------------------------------------------------------------------------------
# label formats


def test_sleap_project_written_by_sleap_io(tmp_path):
    sio = pytest.importorskip("sleap_io")
    from s3k.data.formats.slp import read_slp

    sk = sio.Skeleton(nodes=list(NODES))
    video = sio.Video(filename=str(tmp_path / "cam0.mp4"), open_backend=False)
    frames = [sio.LabeledFrame(video=video, frame_idx=f, instances=[sio.Instance.from_numpy(uv, skeleton=sk)])
              for f, uv in enumerate(s3k_uv())]
    sio.save_slp(sio.Labels(labeled_frames=frames, videos=[video], skeletons=[sk]), str(tmp_path / "p.slp"))
    _close(read_slp(tmp_path / "p.slp", ["cam0"])["cam0"])


def test_sleap_project_of_the_old_corner_format(tmp_path):
    """SLEAP projects before format 1.1 stored a person's points with (0, 0) at the image corner; sleap-io
    moves them by -0.5 px on read, and s3k reads them through it."""
    sio = pytest.importorskip("sleap_io")
    import h5py

    from s3k.data.formats.slp import read_slp

    sk = sio.Skeleton(nodes=list(NODES))
    video = sio.Video(filename=str(tmp_path / "cam0.mp4"), open_backend=False)
    frames = [sio.LabeledFrame(video=video, frame_idx=f, instances=[sio.Instance.from_numpy(uv, skeleton=sk)])
              for f, uv in enumerate(corner(s3k_uv()))]
    sio.save_slp(sio.Labels(labeled_frames=frames, videos=[video], skeletons=[sk]), str(tmp_path / "old.slp"))
    with h5py.File(tmp_path / "old.slp", "r+") as f:  # format 1.0: instances had no tracking score yet
        f["metadata"].attrs["format_id"] = 1.0
        instances = f["instances"][()]
        fields = [n for n in instances.dtype.names if n != "tracking_score"]
        del f["instances"]
        f["instances"] = np.array(instances[fields].tolist(), dtype=[(n, instances.dtype[n]) for n in fields])
    _close(read_slp(tmp_path / "old.slp", ["cam0"])["cam0"])


def test_sleap_analysis_file(tmp_path):
    """SLEAP writes an analysis file from its projects' points as they are (its own convention)."""
    write_sleap(tmp_path / "cam0.analysis.h5", s3k_uv()[..., None], nodes=NODES)
    _close(read_sleap_analysis(tmp_path / "cam0.analysis.h5"))


def _dlc_rows(uv: np.ndarray, scorer: str = "me") -> str:
    rows = ["scorer" + f",{scorer}" * 2 * len(NODES), "bodyparts," + ",".join(f"{k},{k}" for k in NODES),
            "coords" + ",x,y" * len(NODES)]
    rows += [f"labeled-data/rec/img{f:04d}.png," + ",".join(repr(float(v)) for v in uv[f].ravel())
             for f in range(len(uv))]
    return "\n".join(rows) + "\n"


def test_deeplabcut_csv(tmp_path):
    (tmp_path / "CollectedData_me.csv").write_text(_dlc_rows(s3k_uv()))
    _close(read_dlc_csv(tmp_path / "CollectedData_me.csv"))


def test_lightning_pose_csv(tmp_path):
    (tmp_path / "CollectedData_cam0.csv").write_text(_dlc_rows(s3k_uv()))
    _close(read_dlc_csv(find_lightning_pose_csvs(tmp_path, ["cam0"])["cam0"]))


def test_nwb_written_by_pynwb_and_ndx_pose(tmp_path):
    pynwb = pytest.importorskip("pynwb")
    ndx_pose = pytest.importorskip("ndx_pose")
    from s3k.data.formats.nwb import read_nwb

    nwb = pynwb.NWBFile(session_description="pixels", identifier="pixels",
                        session_start_time=datetime(2026, 1, 1, tzinfo=timezone.utc))
    sk = ndx_pose.Skeleton(name="mouse", nodes=NODES, edges=np.zeros((0, 2), dtype=np.uint8))
    behavior = nwb.create_processing_module(name="behavior", description="labels")
    behavior.add(ndx_pose.Skeletons(skeletons=[sk]))
    series = pynwb.image.ImageSeries(name="cam0", external_file=["cam0.mp4"], format="external",
                                     starting_frame=[0], rate=30.0, num_samples=len(X))
    frames = [ndx_pose.TrainingFrame(
        name=f"frame_{f}", annotator="person", source_video=series, source_video_frame_index=np.uint64(f),
        skeleton_instances=ndx_pose.SkeletonInstances(skeleton_instances=[ndx_pose.SkeletonInstance(
            name="mouse", id=np.uint8(0), node_locations=uv, node_visibility=np.ones(len(NODES), bool),
            skeleton=sk)]))
        for f, uv in enumerate(s3k_uv())]
    behavior.add(ndx_pose.PoseTraining(training_frames=ndx_pose.TrainingFrames(training_frames=frames),
                                       source_videos=ndx_pose.SourceVideos(image_series=[series])))
    with pynwb.NWBHDF5IO(str(tmp_path / "labels.nwb"), "w") as io:
        io.write(nwb)
    _close(read_nwb(tmp_path / "labels.nwb", ["cam0"])["cam0"])


def test_openpose_json_is_moved_by_half_a_pixel(tmp_path):
    """OpenPose's keypoints put the top-left pixel's centre at (0.5, 0.5): read 0.5 px up and left."""
    for f, uv in enumerate(corner(s3k_uv())):
        flat = np.concatenate([uv, np.full((len(NODES), 1), 0.9)], axis=1).ravel().tolist()
        data = {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat}]}
        (tmp_path / f"rec_{f:012d}_keypoints.json").write_text(json.dumps(data))
    table = read_openpose_folder(tmp_path)
    table.keypoints = NODES  # OpenPose names 3 points kp0.. kp2
    _close(table)


def test_mmpose_json(tmp_path):
    scores = [0.9] * len(NODES)
    frames = [{"frame_id": f, "instances": [{"keypoints": uv.tolist(), "keypoint_scores": scores}]}
              for f, uv in enumerate(s3k_uv())]
    meta = {"keypoint_id2name": {str(k): n for k, n in enumerate(NODES)}}
    (tmp_path / "results.json").write_text(json.dumps({"meta_info": meta, "instance_info": frames}))
    _close(read_mmpose_json(tmp_path / "results.json"))


def test_deepfly3d_fractions(tmp_path):
    """DeepFly3D's 2D network writes (row, column) fractions of the image: s3k's pixels times the size."""
    uv = s3k_uv()
    fractions = np.stack([uv[..., 1] / H, uv[..., 0] / W], axis=-1)[None]  # (C, T, J, 2)
    with open(tmp_path / "df3d_result.pkl", "wb") as f:
        pickle.dump({"points2d": fractions, "camera_ordering": np.arange(1)}, f)
    table = read_deepfly3d_pose(tmp_path / "df3d_result.pkl", {"camera_0": (W, H)})["camera_0"]
    table.keypoints = NODES
    _close(table)


# ------------------------------------------------------------------------------------------------------------
# calibrations


def _anipose_toml(path, K_file):
    path.write_text(
        "[cam_0]\n"
        'name = "cam0"\n'
        f"size = [{W}, {H}]\n"
        f"matrix = {json.dumps(K_file.tolist())}\n"
        f"distortions = {json.dumps(DIST.tolist())}\n"
        f"rotation = {json.dumps(RVEC.tolist())}\n"
        f"translation = {json.dumps(T.tolist())}\n"
        "\n[metadata]\n"
        'units = "mm"\n'
    )


def test_anipose_calibration_toml(tmp_path):
    """anipose's TOML holds OpenCV's camera: s3k projects with it where OpenCV does."""
    _anipose_toml(tmp_path / "calibration.toml", K)
    rig = read_anipose_calibration(tmp_path / "calibration.toml")
    got = project(rig.cameras[0], torch.as_tensor(X.reshape(-1, 3)))[0].numpy().reshape(s3k_uv().shape)
    assert np.abs(got - s3k_uv()).max() < TOL


def test_calibration_of_the_corner_convention(tmp_path):
    """A calibration whose principal point sits 0.5 px right and down (fitted to corner-convention points):
    declared as such, it projects into s3k's pixels."""
    K_corner = K.copy()
    K_corner[:2, 2] += 0.5
    _anipose_toml(tmp_path / "calibration.toml", K_corner)
    rig = pixels.rig_to_s3k(read_anipose_calibration(tmp_path / "calibration.toml"), "corner")
    got = project(rig.cameras[0], torch.as_tensor(X.reshape(-1, 3)))[0].numpy().reshape(s3k_uv().shape)
    assert np.abs(got - s3k_uv()).max() < TOL


def test_every_format_states_its_convention():
    """The table of conventions names every label format s3k imports and every calibration format."""
    from s3k.data.formats.calibration_files import FORMATS as CALIBRATIONS
    from s3k.data.import_labels import LABEL_FORMATS

    kinds = {cls.kind for cls in LABEL_FORMATS.values()}
    assert kinds | set(CALIBRATIONS) <= set(pixels.FORMATS)
    assert pixels.FORMATS["openpose"][0] == "corner"
    assert {c for k, (c, _) in pixels.FORMATS.items() if k != "openpose"} == {"centre"}


# ------------------------------------------------------------------------------------------------------------
# s3k import --label-pixels / --calibration-pixels


def test_import_declares_files_of_the_corner_convention(import_recording, tmp_path):
    """DeepLabCut CSVs and a calibration both written with (0, 0) at the image corner: declared with
    --label-pixels corner and --calibration-pixels corner, the dataset holds the recording's own labels and
    cameras (in s3k's pixels)."""
    from s3k.cli import main
    from s3k.data import Dataset
    from s3k.data.formats import anipose

    root = import_recording["root"]
    rig = anipose.read_anipose_calibration(root / "calibration.toml")
    a = rig.cameras.numpy()
    K_corner = a["K"].copy()
    K_corner[:, :2, 2] += 0.5
    shifted = pixels.replace(rig, cameras=Cameras.from_numpy(K_corner, a["dist"], a["R"], a["t"],
                                                            dtype=torch.float64))
    anipose.write_anipose_calibration(tmp_path / "calibration.toml", shifted)
    uv = import_recording["uv"]
    csvs = []
    for c, cam in enumerate(CAMS):
        rows = ["scorer" + ",me" * 6, "bodyparts," + ",".join(f"{k},{k}" for k in KEYPOINTS),
                "coords" + ",x,y" * 3]
        rows += [f"labeled-data/rec_{cam}/img{f:04d}.png,"
                 + ",".join("" if np.isnan(v) else repr(float(v) + 0.5) for v in uv[f, c].ravel())
                 for f in range(len(uv))]
        (tmp_path / f"{cam}.csv").write_text("\n".join(rows) + "\n")
        csvs.append(f"{cam}={tmp_path / cam}.csv")
    argv = ["import", "--calibration", str(tmp_path / "calibration.toml"),
            "--videos", *[f"{cam}={root / cam}.mkv" for cam in CAMS], "--dlc", *csvs, "--labelled", "all",
            "--label-pixels", "corner", "--calibration-pixels", "corner", "--out", str(tmp_path / "ds")]
    assert main(argv) == 0
    ds = Dataset.open(tmp_path / "ds")
    ids = ds.frames("labelled")
    got, mask = ds.labels(ids, dtype=np.float64)
    np.testing.assert_allclose(got[mask], uv[ids][mask], atol=1e-9)
    np.testing.assert_allclose(ds.rig(np.float64).numpy()["K"], a["K"], atol=1e-12)
