"""SLEAP projects, NWB (ndx-pose) and the label / track exports: files made here with each format's own
library (sleap-io, pynwb + ndx-pose), imported with ``s3k import`` and compared label by label; exports read
back with those libraries and s3k's readers; round trips s3k -> DLC / Lightning Pose / SLEAP / NWB -> s3k."""

import csv

import numpy as np
import pytest
import torch
from helpers.real_recording import REAL, needs_real
from helpers.synthetic_rig import LAYOUT, project, random_rotation, rig

from s3k.base.errors import UserError
from s3k.cli import main
from s3k.data import Dataset, DatasetWriter, check_dataset
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.formats.dlc import read_dlc_csv
from s3k.data.rig import Rig
from s3k.geometry import Cameras

sio = pytest.importorskip("sleap_io")
pynwb = pytest.importorskip("pynwb")
ndx_pose = pytest.importorskip("ndx_pose")

SIZE, N_FRAMES = 32, 8
CAMS = ["cam0", "cam1", "cam2", "cam3"]
KPS = ("a", "b", "c")


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """A 4-camera rig (metres), ffv1 videos of 8 frames and the true projections ``uv (F, C, K, 2)``."""
    from s3k.data.video import write_video

    root = tmp_path_factory.mktemp("rec")
    K, dist, R, t = rig(SIZE)
    cams = Cameras.from_numpy(K, dist, R, t, dtype=torch.float64)
    write_anipose_calibration(root / "calibration.toml",
                              Rig(list(CAMS), cams, np.array([[SIZE, SIZE]] * 4), "m", {"units": "m"}))
    rng = np.random.default_rng(3)
    uv = np.stack([project(K, R, t, LAYOUT @ random_rotation(rng).T) for _ in range(N_FRAMES)])
    for cam in CAMS:
        frames = [rng.integers(0, 255, (SIZE, SIZE, 3), dtype=np.uint8) for _ in range(N_FRAMES)]
        write_video(root / f"{cam}.mkv", frames, fps=30, codec="ffv1")
    return {"root": root, "uv": uv, "rig": (K, dist, R, t)}


def _import(rec, out, *labels, extra=()):
    root = rec["root"]
    argv = ["import", "--calibration", str(root / "calibration.toml"), "--videos",
            *[f"{cam}={root / cam}.mkv" for cam in CAMS], *labels, "--out", str(out), "--labelled", "all",
            "--min-views", "1", *extra]
    return main(argv)


def _all_labels(path):
    """``(uv (F, C, K, 2) float64 NaN where unlabelled)`` of a dataset over video frames 0..N_FRAMES-1."""
    ds = Dataset.open(path, cache="none")
    problems, _ = check_dataset(path)
    assert not [p for p in problems if p.severity == "error"], problems
    out = np.full((N_FRAMES, len(ds.cameras), len(ds.keypoints), 2), np.nan)
    ids = ds.frames()
    uv, mask = ds.labels(ids, dtype=np.float64)
    out[ids] = np.where(mask[..., None], uv, np.nan)
    return ds, out


# ------------------------------------------------------------------------------------------------------------
# SLEAP projects (.slp)


def _project(path, rec, *, frames=range(6), names=None, tracks=(), predicted=(), skip=None, instances=1,
             cams=None):
    """A SLEAP project with one video per camera named ``names[c]`` and user instances on ``frames``;
    ``predicted`` frames get predicted instances (offset by +1 px); ``skip(c, k)`` leaves a node unlabelled;
    ``cams`` are the recording's camera indices of the videos (default 0, 1, ...)."""
    names = names or [f"/videos/{cam}.mp4" for cam in CAMS]
    sk = sio.Skeleton(list(KPS))
    track_objs = [sio.Track(n) for n in tracks]
    videos = [sio.Video(filename=n, open_backend=False) for n in names]
    lfs = []
    for i, video in enumerate(videos):
        c = cams[i] if cams else i
        for f in sorted(set(frames) | set(predicted)):
            pts = rec["uv"][f, c].copy()
            for k in range(len(KPS)):
                if skip is not None and skip(c, k):
                    pts[k] = np.nan
            insts = []
            if f in frames:
                for i in range(instances if not track_objs else len(track_objs)):
                    track = track_objs[i] if track_objs else None
                    insts.append(sio.Instance.from_numpy(pts + 10 * i, skeleton=sk, track=track))
            if f in predicted:
                insts.append(sio.PredictedInstance.from_numpy(pts + 1, skeleton=sk, score=0.9,
                                                              track=track_objs[0] if track_objs else None))
            lfs.append(sio.LabeledFrame(video=video, frame_idx=f, instances=insts))
    labels = sio.Labels(labeled_frames=lfs, videos=videos, skeletons=[sk], tracks=track_objs)
    sio.save_slp(labels, str(path))
    return path


def test_slp_project_one_video_per_camera(rec, tmp_path, capsys):
    slp = _project(tmp_path / "labels.slp", rec, predicted=[0, 6, 7], skip=lambda c, k: (c, k) == (1, 2))
    assert _import(rec, tmp_path / "ds", "--sleap", str(slp)) == 0
    out = capsys.readouterr().out
    assert "warning: camera cam1: keypoints c have no labels" in out
    ds, uv = _all_labels(tmp_path / "ds")
    assert ds.cameras == CAMS and ds.keypoints == list(KPS)
    assert ds.units == "m" and ds.image_size == (SIZE, SIZE)
    expected = rec["uv"].copy()
    expected[6:] = np.nan  # predictions only: not labels without --accept-predictions
    expected[:, 1, 2] = np.nan
    np.testing.assert_array_equal(uv, expected)  # frame 0: the person's instance, not the prediction
    np.testing.assert_array_equal(ds.frames("labelled"), np.arange(6))
    assert ds.source["importer"] == "sleap"

    assert _import(rec, tmp_path / "pred", "--sleap", str(slp), extra=["--accept-predictions"]) == 0
    _, uv = _all_labels(tmp_path / "pred")
    expected[6:] = rec["uv"][6:] + 1
    expected[:, 1, 2] = np.nan
    np.testing.assert_array_equal(uv, expected)


def test_slp_per_camera_files_and_camera_map(rec, tmp_path):
    files = []
    for c, cam in enumerate(CAMS[:2]):
        single = _project(tmp_path / f"{cam}.slp", rec, names=[f"session/view_{c}.avi"], cams=[c])
        files.append(f"{cam}={single}")
    # Per-camera projects with one video: the video's name does not matter.
    assert _import(rec, tmp_path / "ds", "--sleap", *files) == 0
    _, uv = _all_labels(tmp_path / "ds")
    np.testing.assert_array_equal(uv[:6, :2], rec["uv"][:6, :2])
    assert np.isnan(uv[:, 2:]).all()
    # Per-camera files holding several videos: each camera's entry of --camera-map picks its video.
    both = _project(tmp_path / "both.slp", rec, names=["x/view_0.avi", "x/view_1.avi"])
    assert _import(rec, tmp_path / "both", "--sleap", f"cam0={both}", f"cam1={both}",
                   extra=["--camera-map", "cam0=view_0", "cam1=view_1"]) == 0
    np.testing.assert_array_equal(_all_labels(tmp_path / "both")[1][:6, :2], rec["uv"][:6, :2])
    # One project whose video names are not the cameras': --camera-map (file stem or index).
    names = [f"/data/top_{c}.mp4" for c in range(4)]
    slp = _project(tmp_path / "renamed.slp", rec, names=names)
    with pytest.raises(UserError, match=r"no video matches a camera .*top_0, top_1.*--camera-map"):
        from s3k.data.formats.slp import read_slp

        read_slp(slp, CAMS)
    mapping = ["cam0=top_0", "cam1=top_1.mp4", "cam2=2", "cam3=/data/top_3.mp4"]
    assert _import(rec, tmp_path / "mapped", "--sleap", str(slp), extra=["--camera-map", *mapping]) == 0
    _, uv = _all_labels(tmp_path / "mapped")
    np.testing.assert_array_equal(uv[:6], rec["uv"][:6])


def test_slp_tracks(rec, tmp_path, capsys):
    slp = _project(tmp_path / "two.slp", rec, tracks=("mouse_a", "mouse_b"))
    # Without --sleap-track the most labelled track is imported (the first on a tie), and the import says so.
    assert _import(rec, tmp_path / "x", "--sleap", str(slp)) == 0
    assert ("note: 2 tracks are labelled (frames: mouse_a 24, mouse_b 24); importing mouse_a, the most "
            "labelled (--sleap-track NAME picks another") in capsys.readouterr().out
    _, uv = _all_labels(tmp_path / "x")
    np.testing.assert_array_equal(uv[:6], rec["uv"][:6])
    assert _import(rec, tmp_path / "b", "--sleap", str(slp), extra=["--sleap-track", "mouse_b"]) == 0
    _, uv = _all_labels(tmp_path / "b")
    np.testing.assert_array_equal(uv[:6], rec["uv"][:6] + 10)  # the second animal
    assert _import(rec, tmp_path / "all", "--sleap", str(slp), extra=["--sleap-track", "all"]) == 0
    _, a = _all_labels(tmp_path / "all" / "mouse_a")
    _, b = _all_labels(tmp_path / "all" / "mouse_b")
    np.testing.assert_array_equal(a[:6], rec["uv"][:6])
    np.testing.assert_array_equal(b[:6], rec["uv"][:6] + 10)
    # The analysis HDF5 reader names the option too.
    import h5py

    h5 = tmp_path / "two.analysis.h5"
    with h5py.File(h5, "w") as f:
        tracks = np.full((2, 2, 3, 4), 5.0)  # (tracks, xy, nodes, frames), as SLEAP writes it
        tracks[0, :, :, 1:] = np.nan  # mouse_a labelled in one frame, mouse_b in four
        f["tracks"] = tracks
        f["node_names"] = np.array([k.encode() for k in KPS])
        f["track_names"] = np.array([b"mouse_a", b"mouse_b"])
    assert _import(rec, tmp_path / "h", "--sleap", f"cam0={h5}") == 0
    assert "(frames: mouse_a 1, mouse_b 4); importing mouse_b" in capsys.readouterr().out
    with pytest.raises(UserError, match="2 tracks \\(mouse_a, mouse_b\\); choose one with --sleap-track"):
        from s3k.data.formats.sleap import read_sleap_analysis

        read_sleap_analysis(h5)  # the reader itself does not choose
    # Without tracks, two instances in a frame: choose by index.
    untracked = _project(tmp_path / "untracked.slp", rec, instances=2)
    assert _import(rec, tmp_path / "y", "--sleap", str(untracked)) == 1
    assert "--sleap-track INDEX" in capsys.readouterr().err
    assert _import(rec, tmp_path / "i1", "--sleap", str(untracked), extra=["--sleap-track", "1"]) == 0
    _, uv = _all_labels(tmp_path / "i1")
    np.testing.assert_array_equal(uv[:6], rec["uv"][:6] + 10)


def test_sleap_without_labelled_frames_is_an_error(rec, tmp_path, capsys):
    empty = tmp_path / "empty.slp"
    sio.save_slp(sio.Labels(videos=[sio.Video(filename="cam0.mp4", open_backend=False)],
                            skeletons=[sio.Skeleton(list(KPS))]), str(empty))
    assert _import(rec, tmp_path / "x", "--sleap", f"cam0={empty}") == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [f"s3k import: error: {empty}: no labelled frames (the project has 0 frames "
                                "and 0 instances)"]
    predicted = _project(tmp_path / "pred.slp", rec, frames=[], predicted=[1, 2])
    assert _import(rec, tmp_path / "y", "--sleap", str(predicted)) == 1
    assert "only 8 predicted; pass --accept-predictions" in capsys.readouterr().err
    # The analysis HDF5 reader: a file of zero frames.
    import h5py

    h5 = tmp_path / "zero.analysis.h5"
    with h5py.File(h5, "w") as f:
        f["tracks"] = np.zeros((1, 2, 3, 0))
        f["node_names"] = np.array([k.encode() for k in KPS])
    assert _import(rec, tmp_path / "z", "--sleap", f"cam0={h5}") == 1
    assert f"{h5}: no labelled frames (the file holds 0 frames)" in capsys.readouterr().err


def test_camera_without_labels_is_warned(rec, tmp_path, capsys):
    slp = _project(tmp_path / "three.slp", rec, names=[f"{cam}.mp4" for cam in CAMS[:3]],
                   skip=lambda c, k: k == 2)
    assert _import(rec, tmp_path / "ds", "--sleap", str(slp)) == 0
    out = capsys.readouterr().out.splitlines()
    assert "warning: camera cam3 has no labels (no label file)" in out
    assert "warning: keypoint c has no labels in any camera" in out


# ------------------------------------------------------------------------------------------------------------
# NWB (ndx-pose)


def _nwb_file():
    import datetime

    return pynwb.NWBFile(session_description="test", identifier="test-id",
                         session_start_time=datetime.datetime(2026, 1, 1, tzinfo=datetime.timezone.utc))


def _nwb_training(path, rec, frames=range(5), device_names=None):
    """Training frames per camera in ndx-pose's layout: ImageSeries per camera (device named after it)."""
    nwb = _nwb_file()
    sk = ndx_pose.Skeleton(name="mouse", nodes=KPS, edges=np.array([[0, 1]], dtype=np.uint8))
    behavior = nwb.create_processing_module(name="behavior", description="pose")
    behavior.add(ndx_pose.Skeletons(skeletons=[sk]))
    series, training = [], []
    for c in range(len(CAMS)):
        device = nwb.create_device(name=(device_names or CAMS)[c])
        video = pynwb.image.ImageSeries(name=f"video_{c}", external_file=[f"recording_{c}.mp4"],
                                        format="external", starting_frame=[0], rate=30.0,
                                        num_samples=N_FRAMES, device=device)
        series.append(video)
        for f in frames:
            uv = rec["uv"][f, c].copy()
            seen = np.ones(len(KPS), bool)
            if (c, f) == (2, 1):
                seen[0] = False  # marked not visible: unlabelled
            inst = ndx_pose.SkeletonInstance(name="instance", id=np.uint8(0), node_locations=uv,
                                             node_visibility=seen, skeleton=sk)
            training.append(ndx_pose.TrainingFrame(
                name=f"frame_{c}_{f}",
                skeleton_instances=ndx_pose.SkeletonInstances(skeleton_instances=[inst]),
                source_video=video, source_video_frame_index=np.uint64(f)))
    behavior.add(ndx_pose.PoseTraining(training_frames=ndx_pose.TrainingFrames(training_frames=training),
                                       source_videos=ndx_pose.SourceVideos(image_series=series)))
    with pynwb.NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)
    return path


def test_nwb_training_frames(rec, tmp_path):
    path = _nwb_training(tmp_path / "labels.nwb", rec)
    assert _import(rec, tmp_path / "ds", "--nwb", str(path)) == 0
    ds, uv = _all_labels(tmp_path / "ds")
    assert ds.keypoints == list(KPS) and ds.cameras == CAMS and ds.source["importer"] == "nwb"
    expected = np.full_like(rec["uv"], np.nan)
    expected[:5] = rec["uv"][:5]
    expected[1, 2, 0] = np.nan
    np.testing.assert_array_equal(uv, expected)
    # Device names that differ from the dataset's cameras: --camera-map.
    other = _nwb_training(tmp_path / "other.nwb", rec, device_names=["A", "B", "C", "D"])
    with pytest.raises(UserError, match="no labelled frames for cameras .*A, B, C, D.*--camera-map"):
        from s3k.data.formats.nwb import read_nwb

        read_nwb(other, CAMS)
    mapping = [f"{cam}={name}" for cam, name in zip(CAMS, "ABCD")]
    assert _import(rec, tmp_path / "mapped", "--nwb", str(other), extra=["--camera-map", *mapping]) == 0
    np.testing.assert_array_equal(_all_labels(tmp_path / "mapped")[1], expected)


def test_nwb_pose_estimation_needs_accept_predictions(rec, tmp_path, capsys):
    nwb = _nwb_file()
    sk = ndx_pose.Skeleton(name="mouse", nodes=KPS)
    behavior = nwb.create_processing_module(name="behavior", description="pose")
    behavior.add(ndx_pose.Skeletons(skeletons=[sk]))
    for c, cam in enumerate(CAMS):
        device = nwb.create_device(name=cam)
        series = []
        for k, kp in enumerate(KPS):
            data = rec["uv"][:, c, k].copy()
            data[3] = np.nan
            series.append(ndx_pose.PoseEstimationSeries(
                name=kp, data=data, reference_frame="top left", rate=30.0,
                confidence=np.full(N_FRAMES, 0.9)))
        behavior.add(ndx_pose.PoseEstimation(name=f"pose_{cam}", pose_estimation_series=series, device=device,
                                             skeleton=sk, source_software="DeepLabCut"))
    path = tmp_path / "pred.nwb"
    with pynwb.NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)
    assert _import(rec, tmp_path / "x", "--nwb", str(path)) == 1
    err = capsys.readouterr().err
    assert "pred.nwb: no training frames (labels), only 4 PoseEstimation" in err
    assert "--accept-predictions" in err
    assert _import(rec, tmp_path / "ds", "--nwb", str(path), extra=["--accept-predictions"]) == 0
    _, uv = _all_labels(tmp_path / "ds")
    expected = rec["uv"].copy()
    expected[3] = np.nan
    np.testing.assert_array_equal(uv, expected)


# ------------------------------------------------------------------------------------------------------------
# Exports and round trips


def _dataset(rec, path):
    """A PNG dataset of the recording's frames (ids 0..7), partial labels on frames 0..4."""
    from s3k.data.video import iter_frames

    uv = rec["uv"].copy()
    uv[1, 0, 1] = np.nan
    uv[2, 3] = np.nan
    uv[4, :, 2] = np.nan
    frames = {cam: dict(iter_frames(rec["root"] / f"{cam}.mkv")) for cam in CAMS}
    with DatasetWriter(path, KPS, CAMS, (SIZE, SIZE), "m", calibration=rec["rig"],
                       skeleton=[("a", "b"), ("b", "c")]) as w:
        for f in range(N_FRAMES):
            images = np.stack([frames[cam][f] for cam in CAMS])
            labelled = f < 5
            w.add_frame(f, "labelled" if labelled else "unlabelled", images,
                        labels=uv[f] if labelled else None)
    expected = np.full_like(uv, np.nan)
    expected[:5] = uv[:5]
    return path, expected


def test_export_dlc_and_lightning_pose(rec, tmp_path):
    import cv2

    ds_path, expected = _dataset(rec, tmp_path / "ds")
    ds = Dataset.open(ds_path, cache="none")
    assert main(["export-labels", str(ds_path), "--format", "dlc", "--out", str(tmp_path / "dlc")]) == 0
    for c, cam in enumerate(CAMS):
        path = tmp_path / "dlc" / "labeled-data" / cam / "CollectedData_s3k.csv"
        rows = list(csv.reader(path.open()))
        assert rows[0][:3] == ["scorer", "s3k", "s3k"] and rows[1][:3] == ["bodyparts", "a", "a"]
        assert rows[2][:3] == ["coords", "x", "y"]
        table = read_dlc_csv(path)
        assert table.keypoints == list(KPS)
        labelled = [f for f in range(5) if np.isfinite(expected[f, c]).any()]
        np.testing.assert_array_equal(table.frame_ids, labelled)
        np.testing.assert_array_equal(table.uv, expected[labelled, c])  # exact: full precision text
        image = cv2.imread(str(tmp_path / "dlc" / rows[3][0]))[..., ::-1]
        np.testing.assert_array_equal(image, ds.images([labelled[0]])[0, c])
    assert main(["export-labels", str(ds_path), "--format", "lightning-pose", "--out", str(tmp_path / "lp"),
                 "--no-images"]) == 0
    tables = [read_dlc_csv(tmp_path / "lp" / f"CollectedData_{cam}.csv") for cam in CAMS]
    for c, table in enumerate(tables):  # the same frames on the same rows of every view
        np.testing.assert_array_equal(table.frame_ids, np.arange(5))
        np.testing.assert_array_equal(table.uv, expected[:5, c])
    assert not (tmp_path / "lp" / "labeled-data").exists()
    # An existing file is not replaced without --overwrite.
    again = ["export-labels", str(ds_path), "--format", "lightning-pose", "--out", str(tmp_path / "lp")]
    assert main(again) == 1
    assert main([*again, "--overwrite"]) == 0


def test_export_sleap_and_nwb_read_by_their_libraries(rec, tmp_path):
    ds_path, expected = _dataset(rec, tmp_path / "ds")
    slp = tmp_path / "labels.slp"
    assert main(["export-labels", str(ds_path), "--format", "sleap", "--out", str(slp)]) == 0
    labels = sio.load_slp(str(slp), open_videos=False)
    assert labels.skeletons[0].node_names == list(KPS)
    session = labels.sessions[0]
    assert [cam.name for cam in session.camera_group.cameras] == CAMS
    np.testing.assert_allclose(session.camera_group.cameras[1].matrix, rec["rig"][0][1])
    for lf in labels.labeled_frames:
        c = [cam.name for cam in session.camera_group.cameras].index(session.get_camera(lf.video).name)
        np.testing.assert_array_equal(lf.user_instances[0].numpy(), expected[lf.frame_idx, c])
    assert len(labels.labeled_frames) == 5 * 4 - 1  # frame 2 of cam3 has no label
    # The videos are the dataset's PNG folders, frame index = frame id.
    assert labels.videos[0].filename == str((ds_path / "images" / "cam0").resolve())

    nwb_path = tmp_path / "labels.nwb"
    assert main(["export-labels", str(ds_path), "--format", "nwb", "--out", str(nwb_path)]) == 0
    with pynwb.NWBHDF5IO(str(nwb_path), "r") as io:
        nwb = io.read()
        assert isinstance(nwb.devices["cam2"], ndx_pose.CalibratedCamera)
        np.testing.assert_allclose(nwb.devices["cam2"].rotation_matrix[:], rec["rig"][2][2])
        frames = nwb.processing["behavior"]["PoseTraining"].training_frames.training_frames
        assert len(frames) == 19
        frame = frames["cam1_frame_000004"]
        inst = frame.skeleton_instances.skeleton_instances["instance"]
        assert list(inst.skeleton.nodes[:]) == list(KPS)
        np.testing.assert_array_equal(inst.node_visibility[:], [True, True, False])
        np.testing.assert_array_equal(inst.node_locations[:2], expected[4, 1, :2])
        assert int(frame.source_video_frame_index) == 4 and frame.source_video.name == "cam1"


@pytest.mark.parametrize("fmt", ["dlc", "lightning-pose", "sleap", "nwb"])
def test_round_trip_keeps_every_label(rec, tmp_path, fmt):
    ds_path, expected = _dataset(rec, tmp_path / "ds")
    out = tmp_path / {"sleap": "x.slp", "nwb": "x.nwb"}.get(fmt, "export")
    assert main(["export-labels", str(ds_path), "--format", fmt, "--out", str(out), "--no-images"]) == 0
    labels = {
        "dlc": ["--dlc", *[f"{cam}={out}/labeled-data/{cam}/CollectedData_s3k.csv" for cam in CAMS]],
        "lightning-pose": ["--lightning-pose", str(out)],
        "sleap": ["--sleap", str(out)],
        "nwb": ["--nwb", str(out)],
    }[fmt]
    assert _import(rec, tmp_path / "back", *labels) == 0
    ds, uv = _all_labels(tmp_path / "back")
    assert ds.keypoints == list(KPS) and ds.cameras == CAMS
    np.testing.assert_array_equal(np.isnan(uv), np.isnan(expected))
    np.testing.assert_allclose(uv, expected, rtol=0, atol=1e-9)


def test_round_trip_through_source_videos_maps_pixels_back(rec, tmp_path):
    """A dataset imported with a resize refers to the source videos; the export is in their pixels."""
    slp = _project(tmp_path / "labels.slp", rec)
    assert _import(rec, tmp_path / "half", "--sleap", str(slp), extra=["--size", "16,16"]) == 0
    out = tmp_path / "again.slp"
    assert main(["export-labels", str(tmp_path / "half"), "--format", "sleap", "--out", str(out)]) == 0
    labels = sio.load_slp(str(out), open_videos=False)
    assert labels.videos[0].filename == str((rec["root"] / "cam0.mkv").resolve())
    lf = next(lf for lf in labels.labeled_frames if lf.frame_idx == 3 and lf.video is labels.videos[1])
    np.testing.assert_allclose(lf.user_instances[0].numpy(), rec["uv"][3, 1], atol=1e-9)
    camera = labels.sessions[0].camera_group.cameras[1]
    np.testing.assert_allclose(camera.matrix, rec["rig"][0][1], atol=1e-9)


def test_export_tracks_to_nwb(rec, tmp_path, capsys):
    from s3k.data.formats.nwb import read_nwb_tracks
    from s3k.data.tracks_csv import csv_header

    X = np.arange(3 * len(KPS) * 3, dtype=np.float64).reshape(3, len(KPS), 3) / 7
    X[1, 2] = np.nan
    fnums = [10, 11, 13]
    path = tmp_path / "tracks.csv"
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(csv_header(KPS))
        for i, fnum in enumerate(fnums):
            row = []
            for k in range(len(KPS)):
                row += [repr(float(v)) if np.isfinite(v) else "nan" for v in X[i, k]] + ["0.5", "3", "0.75"]
            writer.writerow(row + [str(fnum)])
    out = tmp_path / "tracks.nwb"
    code = main(["export-tracks", str(path), "--format", "nwb", "--out", str(out), "--fps", "50",
                 "--calibration", str(rec["root"] / "calibration.toml")])
    assert code == 0 and "units m" in capsys.readouterr().out
    names, times, Y, conf, unit = read_nwb_tracks(out)
    assert names == list(KPS) and unit == "m"
    np.testing.assert_allclose(times, np.array(fnums) / 50)
    np.testing.assert_allclose(Y, X, atol=1e-6)  # the CSV keeps 8 significant digits
    assert np.isnan(Y[1, 2]).all() and np.isfinite(Y[0]).all()
    np.testing.assert_array_equal(conf, 0.75)
    with pynwb.NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        np.testing.assert_allclose(nwb.devices["cam3"].intrinsic_matrix[:], rec["rig"][0][3])
    assert main(["export-tracks", str(path), "--format", "nwb", "--out", str(out), "--fps", "50"]) == 1
    assert "--overwrite" in capsys.readouterr().err


def test_export_tracks_never_guesses_the_unit(tmp_path, capsys):
    """Without --calibration the unit comes from what s3k track / predict wrote beside the CSV, or --units;
    with neither the export is refused (millimetres were written as metres)."""
    from s3k.data.formats.nwb import read_nwb_tracks
    from s3k.data.tracks_csv import csv_header, write_source

    path = tmp_path / "points3d.csv"
    path.write_text(",".join(csv_header(["nose"])) + "\n1.5,2.5,3.5,0.4,2,0.9,0\n")
    out = tmp_path / "tracks.nwb"
    argv = ["export-tracks", str(path), "--format", "nwb", "--out", str(out), "--fps", "30"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "the unit of its points is not known" in err and "--units" in err and len(err.splitlines()) == 1
    assert not out.exists()
    write_source(path, "mm", run="run-s3k", calibration="calibration.toml")  # as s3k track does
    assert main(argv) == 0 and "units mm" in capsys.readouterr().out
    assert read_nwb_tracks(out)[4] == "mm"
    assert main([*argv, "--overwrite", "--units", "cm"]) == 0  # said explicitly: used, with a warning
    assert "points are in mm" in capsys.readouterr().err and read_nwb_tracks(out)[4] == "cm"


@needs_real
def test_real_sleap_project_matches_its_analysis_file():
    """SLEAP's own files of the real recording: the project's predictions are the analysis file's points."""
    from s3k.data.formats.sleap import read_sleap_analysis
    from s3k.data.formats.slp import read_slp

    slp = REAL / "back" / "minimal_back_proofread.slp"
    with pytest.raises(UserError, match="only 120 predicted; pass --accept-predictions"):
        read_slp(slp, ["back"])
    table = read_slp(slp, ["back"], predictions=True)["back"]  # one video (a Windows path): camera back
    analysis = read_sleap_analysis(REAL / "back" / "minimal_back_proofread.analysis.h5")
    assert table.keypoints == analysis.keypoints and len(table.keypoints) == 15
    np.testing.assert_array_equal(table.dense(120), analysis.uv)


# ------------------------------------------------------------------------------------------------------------
# The skeleton: imported from SLEAP, DeepLabCut and anipose, exported to SLEAP and DeepLabCut

EDGES = [("a", "b"), ("b", "c")]


@pytest.mark.parametrize("fmt", ["dlc", "sleap", "nwb"])
def test_skeleton_round_trips_through_sleap_dlc_and_nwb(rec, tmp_path, fmt):
    """s3k -> DLC project / SLEAP project / NWB (read by PyYAML / sleap-io / pynwb as those tools read them)
    -> s3k."""
    import yaml

    ds_path, _ = _dataset(rec, tmp_path / "ds")
    assert Dataset.open(ds_path, cache="none").skeleton == EDGES
    out = tmp_path / {"sleap": "x.slp", "nwb": "x.nwb"}.get(fmt, "export")
    assert main(["export-labels", str(ds_path), "--format", fmt, "--out", str(out), "--no-images"]) == 0
    if fmt == "nwb":
        with pynwb.NWBHDF5IO(str(out), "r") as io:
            skeleton = io.read().processing["behavior"]["Skeletons"].skeletons["s3k"]
            np.testing.assert_array_equal(skeleton.edges[:], [[0, 1], [1, 2]])
        labels = ["--nwb", str(out)]
    elif fmt == "sleap":
        assert sio.load_slp(str(out), open_videos=False).skeletons[0].edge_names == EDGES
        labels = ["--sleap", str(out)]
    else:
        config = yaml.safe_load((out / "config.yaml").read_text())
        assert config["bodyparts"] == list(KPS) and config["skeleton"] == [list(e) for e in EDGES]
        assert set(config["video_sets"]) == set(CAMS) and config["scorer"] == "s3k"
        labels = ["--dlc", *[f"{cam}={out}/labeled-data/{cam}/CollectedData_s3k.csv" for cam in CAMS]]
    assert _import(rec, tmp_path / "back", *labels) == 0
    assert Dataset.open(tmp_path / "back", cache="none").skeleton == EDGES


def test_sleap_edges_are_imported_from_projects_and_analysis_files(rec, tmp_path, capsys):
    import h5py

    slp = _project(tmp_path / "labels.slp", rec)
    labels = sio.load_slp(str(slp), open_videos=False)
    labels.skeletons[0].add_edge("c", "a")
    sio.save_slp(labels, str(slp))
    assert _import(rec, tmp_path / "ds", "--sleap", str(slp)) == 0
    assert f"skeleton: 1 edges from {slp}" in capsys.readouterr().out
    assert Dataset.open(tmp_path / "ds", cache="none").skeleton == [("c", "a")]
    # --keypoints leaves out the edges to the keypoints it drops
    assert _import(rec, tmp_path / "ab", "--sleap", str(slp), extra=["--keypoints", "a,b"]) == 0
    assert "skeleton: 0 edges" in capsys.readouterr().out
    assert Dataset.open(tmp_path / "ab", cache="none").skeleton == []

    files = []
    for c, cam in enumerate(CAMS):  # SLEAP's analysis layout: tracks (tracks, 2, nodes, frames)
        path = tmp_path / f"{cam}.analysis.h5"
        with h5py.File(path, "w") as f:
            f["tracks"] = rec["uv"][:, c].transpose(2, 1, 0)[None]
            f["node_names"] = np.array([k.encode() for k in KPS])
            f["edge_names"] = np.array([[b"a", b"b"], [b"b", b"c"]])
            f["edge_inds"] = np.array([[0, 1], [1, 2]])
        files.append(f"{cam}={path}")
    assert _import(rec, tmp_path / "h5", "--sleap", *files) == 0
    assert Dataset.open(tmp_path / "h5", cache="none").skeleton == EDGES


def test_skeleton_from_an_anipose_project_and_from_a_file_given(rec, tmp_path, capsys):
    import shutil

    ds_path, _ = _dataset(rec, tmp_path / "ds")
    assert main(["export-labels", str(ds_path), "--format", "dlc", "--out", str(tmp_path / "csv"),
                 "--no-images"]) == 0
    (tmp_path / "csv" / "config.yaml").unlink()  # CSVs alone: no skeleton of their own
    dlc = ["--dlc", *[f"{cam}={tmp_path}/csv/labeled-data/{cam}/CollectedData_s3k.csv" for cam in CAMS]]
    project = tmp_path / "project"
    (project / "session1" / "calibration").mkdir(parents=True)
    calibration = project / "session1" / "calibration" / "calibration.toml"
    shutil.copy(rec["root"] / "calibration.toml", calibration)
    (project / "config.toml").write_text('[labeling]\nscheme = [["c", "b", "a"]]\n')
    argv = ["import", "--calibration", str(calibration), "--videos",
            *[f"{cam}={rec['root'] / cam}.mkv" for cam in CAMS], *dlc, "--labelled", "all",
            "--min-views", "1"]
    assert main([*argv, "--out", str(tmp_path / "anipose")]) == 0
    assert f"skeleton: 2 edges from {project / 'config.toml'}" in capsys.readouterr().out
    assert Dataset.open(tmp_path / "anipose", cache="none").skeleton == [("c", "b"), ("b", "a")]
    # --skeleton takes it from any of those files, here another dataset
    assert main([*argv, "--out", str(tmp_path / "given"), "--skeleton", str(ds_path)]) == 0
    assert Dataset.open(tmp_path / "given", cache="none").skeleton == EDGES
    (tmp_path / "bad.yaml").write_text("skeleton:\n- [a, nose]\n")
    assert main([*argv, "--out", str(tmp_path / "bad"), "--skeleton", str(tmp_path / "bad.yaml")]) == 1
    err = capsys.readouterr().err
    assert "bad.yaml: skeleton edge a-nose names 'nose', which is not a keypoint (a, b, c)" in err
    assert len(err.strip().splitlines()) <= 2 and not (tmp_path / "bad").exists()


def test_dataset_skeleton_is_checked_on_load(rec, tmp_path):
    import json

    ds_path, _ = _dataset(rec, tmp_path / "ds")
    meta = json.loads((ds_path / "s3k.json").read_text())
    for bad, message in (([["a", "nose"]], "unknown keypoint 'nose'"),
                         ([["b", "b"]], "joins a keypoint to itself"),
                         ([["a"]], "list of \\[keypoint, keypoint\\] pairs")):
        (ds_path / "s3k.json").write_text(json.dumps({**meta, "skeleton": bad}))
        with pytest.raises(UserError, match=message):
            Dataset.open(ds_path, cache="none")


@needs_real
def test_real_recording_sleap_files_carry_the_skeleton():
    from s3k.data.formats.skeleton import read_skeleton
    from s3k.data.formats.sleap import read_sleap_analysis
    from s3k.data.formats.slp import read_slp

    slp = REAL / "back" / "minimal_back_proofread.slp"
    table = read_slp(slp, ["back"], predictions=True)["back"]
    analysis = read_sleap_analysis(REAL / "back" / "minimal_back_proofread.analysis.h5")
    assert len(table.skeleton) == 14 and ("Head", "Nose") in table.skeleton
    assert sorted(analysis.skeleton) == sorted(table.skeleton) == sorted(read_skeleton(slp))
