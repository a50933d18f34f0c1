"""``s3k import`` of the other formats of a rig: calibrations (Qualisys, OpenCV / JARVIS, DeepFly3D), image
sequences, 2D poses (OpenPose, MMPose, DeepFly3D), recordings without labels, video regions, and the failures
a user met (truncated videos, partial imports, keypoint sets that differ, the wrong TOML file).

Every file is written here from the format's published layout, for the 3-camera recording of
``helpers.recordings`` (the ``import_recording`` fixture)."""

from __future__ import annotations

import json
import pickle

import cv2
import numpy as np
import pytest
from helpers.recordings import (
    CAMS,
    H_IMG,
    KEYPOINTS,
    N_FRAMES,
    W_IMG,
    assert_labels,
    assert_same_cameras,
    df3d_calib,
    import_videos,
    recording_rig,
    validated,
    write_sleap,
)

from s3k.base.errors import UserError
from s3k.cli import main, showing_library_messages
from s3k.data import check_dataset
from s3k.data.formats import anipose
from s3k.data.formats.calibration_files import calibration_format, read_calibration
from s3k.data.formats.deepfly3d import JOINTS, camera_sees_joint, read_deepfly3d_pose
from s3k.data.formats.safe_pickle import load_pickle


def _sleap(import_recording, names=CAMS):
    return ["--sleap", *[f"{n}={import_recording['root'] / cam}.analysis.h5" for n, cam in zip(names, CAMS)]]


# ------------------------------------------------------------------------------------------------------------
# Calibrations


def write_qca(path, rig):
    """A Qualisys .qca.txt of ``rig`` (mm), the inverse of Pose2Sim's conversion."""
    cams = rig.cameras.numpy()
    flip = np.diag([1.0, -1.0, -1.0])
    lines = ['<?xml version="1.0" encoding="ASCII"?>', '<calibration source="test.qca" type="regular">',
             "  <cameras>"]
    for c, name in enumerate(rig.names):
        K, d, R, t = (cams[k][c].tolist() for k in ("K", "dist", "R", "t"))
        K, d, R, t = np.array(K), d, np.array(R), np.array(t)
        W, H = rig.size[c]
        orient = (flip @ R).tolist()
        pos = (-R.T @ t).tolist()
        rot = " ".join(f'r{i + 1}{j + 1}="{orient[i][j]!r}"' for i in range(3) for j in range(3))
        lines += [
            f'    <camera active="1" serial="{name}" model="Miqus Video" avg-residual="0.3">',
            f'      <fov_video left="0" top="0" right="{W - 1}" bottom="{H - 1}"/>',
            f'      <transform x="{pos[0]!r}" y="{pos[1]!r}" z="{pos[2]!r}" {rot}/>',
            f'      <intrinsic focalLengthU="{float(K[0, 0]) * 64!r}" focalLengthV="{float(K[1, 1]) * 64!r}" '
            f'centerPointU="{float(K[0, 2]) * 64!r}" centerPointV="{float(K[1, 2]) * 64!r}" '
            f'radialDistortion1="{d[0] * 64!r}" radialDistortion2="{d[1] * 64!r}" radialDistortion3="0" '
            f'tangentalDistortion1="{d[2] * 64!r}" tangentalDistortion2="{d[3] * 64!r}"/>',
            "    </camera>",
        ]
    lines += ["  </cameras>", "</calibration>"]
    path.write_text("\n".join(lines) + "\n")


def test_import_qualisys_calibration(import_recording, tmp_path):
    rig = recording_rig(import_recording)
    qca = tmp_path / "rig.qca.txt"
    write_qca(qca, rig)
    assert calibration_format(qca) == "qualisys"
    read = read_calibration(qca)
    assert read.names == CAMS and read.units == "mm"
    np.testing.assert_array_equal(read.size, rig.size)
    assert import_videos(import_recording, qca, tmp_path / "ds", *_sleap(import_recording), "--labelled",
                         "all") == 0
    ds = validated(tmp_path / "ds")
    assert ds.cameras == CAMS and ds.keypoints == KEYPOINTS and ds.units == "mm"
    assert len(ds.frames("labelled")) == N_FRAMES
    assert_same_cameras(ds, rig)
    assert_labels(ds, import_recording)


def test_import_jarvis_yaml_folder_and_opencv_xml(import_recording, tmp_path):
    rig = recording_rig(import_recording)
    cams = rig.cameras.numpy()
    folder = tmp_path / "jarvis"
    folder.mkdir()
    for c, name in enumerate(CAMS):  # JARVIS: K and R stored transposed, no image size
        fs = cv2.FileStorage(str(folder / f"{name}.yaml"), cv2.FILE_STORAGE_WRITE)
        fs.write("intrinsicMatrix", cams["K"][c].T)
        fs.write("distortionCoefficients", cams["dist"][c].reshape(1, -1))
        fs.write("R", cams["R"][c].T)
        fs.write("T", cams["t"][c].reshape(3, 1))
        fs.release()
    read = read_calibration(folder)
    assert read.names == sorted(CAMS) and read.units == "unknown"
    np.testing.assert_array_equal(read.size, 0)  # the videos give it
    assert import_videos(import_recording, folder, tmp_path / "ds", *_sleap(import_recording), "--labelled",
                         "all", "--units", "mm") == 0
    ds = validated(tmp_path / "ds")
    assert ds.cameras == CAMS and ds.units == "mm" and ds.image_size == (W_IMG, H_IMG)
    assert_same_cameras(ds, rig)
    assert_labels(ds, import_recording)
    # A plain OpenCV XML file: one camera, named by the file, not transposed, with its image size.
    xml = tmp_path / "north.xml"
    fs = cv2.FileStorage(str(xml), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", cams["K"][0])
    fs.write("dist_coeffs", cams["dist"][0])
    fs.write("rvec", cv2.Rodrigues(cams["R"][0])[0])
    fs.write("tvec", cams["t"][0])
    fs.write("image_width", W_IMG)
    fs.write("image_height", H_IMG)
    fs.release()
    one = read_calibration(xml)
    assert one.names == ["north"] and one.size.tolist() == [[W_IMG, H_IMG]]
    np.testing.assert_allclose(one.cameras.numpy()["R"][0], cams["R"][0], atol=1e-12)
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(UserError, match=r"bad.yaml: not a camera calibration: no field intrinsicMatrix"):
        read_calibration(bad)


def test_import_deepfly3d_pickles(import_recording, tmp_path):
    rig = recording_rig(import_recording)
    uv = import_recording["uv"]  # (F, C, K, 2)
    points2d = np.stack([uv[..., 1] / H_IMG, uv[..., 0] / W_IMG], axis=-1).transpose(1, 0, 2, 3)
    result = {**df3d_calib(rig), "points2d": np.nan_to_num(points2d), "camera_ordering": np.arange(3)}
    with open(tmp_path / "df3d_result.pkl", "wb") as f:
        pickle.dump(result, f)
    with open(tmp_path / "calib.pkl", "wb") as f:
        pickle.dump(df3d_calib(rig), f)
    read = read_calibration(tmp_path / "calib.pkl")
    assert read.names == ["camera_0", "camera_1", "camera_2"]
    videos = {f"camera_{c}": import_recording["root"] / f"{cam}.mkv" for c, cam in enumerate(CAMS)}
    code = import_videos(import_recording, tmp_path / "df3d_result.pkl", tmp_path / "ds", "--deepfly3d",
                         str(tmp_path / "df3d_result.pkl"), "--labelled", "all", "--units", "mm",
                         videos=videos)
    assert code == 0
    ds = validated(tmp_path / "ds")
    assert ds.cameras == list(videos) and ds.keypoints == ["joint_0", "joint_1", "joint_2"]
    assert_same_cameras(ds, rig)
    assert_labels(ds, import_recording, atol=1e-4)


def test_deepfly3d_visibility_rule(tmp_path):
    """Each camera keeps the joints of its side only (DeepFly3D's camera_see_joint)."""
    T = 2
    points = np.full((7, T, len(JOINTS), 2), 0.5)
    with open(tmp_path / "r.pkl", "wb") as f:
        pickle.dump({"points2d": points}, f)
    tables = read_deepfly3d_pose(tmp_path / "r.pkl", {f"camera_{c}": (960, 480) for c in range(7)})
    seen = {cam: np.isfinite(t.uv[0, :, 0]) for cam, t in tables.items()}
    idx = {name: j for j, name in enumerate(JOINTS)}
    assert seen["camera_0"][idx["RF_body_coxa"]] and not seen["camera_0"][idx["LF_body_coxa"]]
    assert seen["camera_6"][idx["LH_tarsus_tip"]] and not seen["camera_6"][idx["RH_tarsus_tip"]]
    assert not seen["camera_3"][idx["RF_body_coxa"]] and seen["camera_3"][idx["RF_tibia_tarsus"]]
    assert not seen["camera_3"][idx["RH_tibia_tarsus"]]  # the hind legs are hidden from the middle
    assert seen["camera_1"][idx["R_stripe_0"]] and not seen["camera_2"][idx["R_stripe_0"]]
    assert not seen["camera_4"][idx["L_stripe_1"]] and seen["camera_5"][idx["L_stripe_1"]]
    assert sum(camera_sees_joint(0, j) for j in range(len(JOINTS))) == 19
    np.testing.assert_allclose(tables["camera_0"].uv[0, idx["RF_body_coxa"]], [480.0, 240.0])


class _Boom:
    def __reduce__(self):
        import os

        return os.system, ("echo unpickled > /dev/null",)


def test_pickles_load_with_a_restricted_unpickler(tmp_path):
    path = tmp_path / "calib.pkl"
    with open(path, "wb") as f:
        pickle.dump({0: {"R": _Boom()}}, f)
    with pytest.raises(UserError, match=r"calib.pkl: the pickle asks for (posix|os)\.system"):
        load_pickle(path)
    code = main(["import", "--calibration", str(path), "--videos", "camera_0=a.mp4", "--keypoints", "a",
                 "--out", str(tmp_path / "ds")])
    assert code == 1
    (tmp_path / "text.pkl").write_bytes(b"\x80\x04garbage")
    with pytest.raises(UserError, match=r"text.pkl: not a readable pickle"):
        load_pickle(tmp_path / "text.pkl")
    arrays = {"a": np.arange(3.0), "b": [1, 2.5, "x"], "c": np.float32(2.0)}
    with open(tmp_path / "ok.pkl", "wb") as f:
        pickle.dump(arrays, f, protocol=5)
    back = load_pickle(tmp_path / "ok.pkl")
    np.testing.assert_array_equal(back["a"], arrays["a"])
    assert back["b"] == [1, 2.5, "x"] and back["c"] == np.float32(2.0)


def test_pose2sim_config_is_not_an_anipose_calibration(tmp_path, capsys):
    config = tmp_path / "Config.toml"
    config.write_text('[project]\nmulti_person = false\nframe_rate = "auto"\n\n[pose]\n'
                      'vid_img_extension = "mp4"\n\n[calibration]\ncalibration_type = "convert"\n'
                      '[calibration.convert]\nconvert_from = "qualisys"\n')
    code = main(["import", "--calibration", str(config), "--videos", "a=a.mp4", "--keypoints", "x",
                 "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1
    assert f"{config}: not an anipose calibration" in err and "Pose2Sim Config.toml" in err


def test_units_from_the_anipose_project_config(import_recording, tmp_path):
    session = tmp_path / "project" / "session1" / "calibration"
    session.mkdir(parents=True)
    text = (import_recording["root"] / "calibration.toml").read_text()
    text = text[: text.index("[metadata]")]  # no units, no board in the file
    (session / "calibration.toml").write_text(text)
    assert anipose.read_anipose_calibration(session / "calibration.toml").units == "unknown"
    (tmp_path / "project" / "config.toml").write_text(
        "[calibration]\nboard_type = \"charuco\"\nboard_size = [10, 7]\nboard_square_side_length = 25\n")
    assert anipose.read_anipose_calibration(session / "calibration.toml").units == "mm"
    assert anipose.read_anipose_calibration(session / "calibration.toml", units="cm").units == "cm"


# ------------------------------------------------------------------------------------------------------------
# Videos: image sequences, decoded frame counts, regions of the calibrated image


def _sequences(import_recording, root):
    """The recording's frames as PNG folders, given as a folder, a glob and a printf pattern."""
    from s3k.data.video import extract_frames

    for cam in CAMS:
        extract_frames(import_recording["root"] / f"{cam}.mkv", root / cam, pattern="img_{:04d}.png")
    return {"north": root / "north", "east": root / "east" / "*.png",
            "south": root / "south" / "img_%04d.png"}


def test_import_image_sequences_like_videos(import_recording, tmp_path):
    seqs = _sequences(import_recording, tmp_path / "seq")
    calib = import_recording["root"] / "calibration.toml"
    args = (*_sleap(import_recording), "--labelled", "3", "--test", "2", "--seed", "4", "--scale", "0.5")
    assert import_videos(import_recording, calib, tmp_path / "from_seq", *args, videos=seqs) == 0
    assert import_videos(import_recording, calib, tmp_path / "from_video", *args) == 0
    a, b = validated(tmp_path / "from_seq"), validated(tmp_path / "from_video")
    for split in ("labelled", "test", "unlabelled"):
        np.testing.assert_array_equal(a.frames(split), b.frames(split))
    ids = a.frames()
    np.testing.assert_array_equal(a.images(ids), b.images(ids))
    np.testing.assert_array_equal(a.labels(ids)[0], b.labels(ids)[0])
    from s3k.data import video

    assert video.frame_count(seqs["south"]) == N_FRAMES and video.frame_size(seqs["east"]) == (W_IMG, H_IMG)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(UserError, match="empty: folder has no image files"):
        video.frame_count(empty)


def _truncated_video(path, frames):
    """An mp4 whose header (written first) counts ``len(frames)`` frames, cut so that the last cannot
    decode."""
    from fractions import Fraction

    import av

    container = av.open(str(path), "w", options={"movflags": "faststart"})
    stream = container.add_stream("mpeg4", rate=Fraction(10))
    stream.width, stream.height, stream.pix_fmt = W_IMG, H_IMG, "yuv420p"
    sizes = []
    for image in frames:
        for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
            sizes.append(packet.size)
            container.mux(packet)
    for packet in stream.encode():
        sizes.append(packet.size)
        container.mux(packet)
    container.close()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - sizes[-1]])  # the media data comes last: drop the last frame's


def test_frame_counts_come_from_decoding(import_recording, tmp_path, capsys):
    from s3k.data import video

    short = tmp_path / "north.mp4"
    _truncated_video(short, import_recording["frames"]["north"][:3])
    assert video.frame_count(short) == 3 and video.frame_count(short, exact=True) == 2
    videos = {"north": short, "east": import_recording["root"] / "east.mkv"}
    code = import_videos(import_recording, import_recording["root"] / "calibration.toml", tmp_path / "ds",
                         "--keypoints", "head,body", videos=videos)
    err = capsys.readouterr().err
    assert code == 0, err
    assert f"{short}: the header says 3 frames but 2 decode; using 2" in err
    ds = validated(tmp_path / "ds")
    np.testing.assert_array_equal(ds.frames("unlabelled"), [0, 1])


def test_video_region_declares_a_cropped_video(import_recording, tmp_path, capsys):
    from s3k.data.video import write_video

    rig = recording_rig(import_recording)
    videos = {}
    for cam in CAMS:  # videos 4 rows shorter: 2 rows of the calibrated image cut at the top and bottom
        videos[cam] = tmp_path / f"{cam}.mkv"
        write_video(videos[cam], [f[2:-2] for f in import_recording["frames"][cam]], codec="ffv1")
    calib = import_recording["root"] / "calibration.toml"
    assert import_videos(import_recording, calib, tmp_path / "x", "--keypoints", "head", videos=videos) == 1
    err = capsys.readouterr().err
    assert f"video is {W_IMG}x{H_IMG - 4}" in err and "(3 cameras differ)" in err
    assert f"--video-region north=0,0,{W_IMG},{H_IMG - 4} east=0,0,{W_IMG},{H_IMG - 4} south=" in err
    regions = [f"{cam}=0,2,{W_IMG},{H_IMG - 2}" for cam in CAMS]
    assert import_videos(import_recording, calib, tmp_path / "ds", "--keypoints", "head", "--video-region",
                         *regions, videos=videos) == 0
    ds = validated(tmp_path / "ds")
    assert ds.image_size == (W_IMG, H_IMG - 4)
    K = ds.rig(np.float64).numpy()["K"]
    ref = rig.cameras.numpy()["K"]
    np.testing.assert_allclose(K[:, 1, 2], ref[:, 1, 2] - 2)  # the principal point moves with the rows cut
    np.testing.assert_allclose(K[:, 0], ref[:, 0])
    np.testing.assert_array_equal(ds.images([5])[0, 1], import_recording["frames"]["east"][5][2:-2])


# ------------------------------------------------------------------------------------------------------------
# 2D poses: OpenPose, MMPose


def _person(uv, scores):
    """OpenPose's flat x, y, score list; a missing point is 0, 0, 0 as OpenPose writes it."""
    flat = []
    for (u, v), s in zip(uv, scores):
        flat += [0.0, 0.0, 0.0] if not np.isfinite(u) else [float(u), float(v), float(s)]
    return flat


def test_import_openpose_json(import_recording, tmp_path):
    uv = import_recording["uv"]
    rng = np.random.default_rng(3)
    for c, cam in enumerate(CAMS):
        folder = tmp_path / "op" / cam
        folder.mkdir(parents=True)
        for f in range(N_FRAMES):
            scores = np.full(3, 0.9)
            if f == 7:
                scores[2] = 0.2  # below --min-score: unlabelled
            decoy = _person(rng.uniform(0, 40, (3, 2)), [0.3, 0.3, 0.3])  # a less confident person
            real = _person(uv[f, c] + 0.5, scores)  # OpenPose's pixels: the top-left pixel's centre at 0.5
            data = {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": decoy},
                                               {"person_id": [-1], "pose_keypoints_2d": real}]}
            (folder / f"rec_{f:012d}_keypoints.json").write_text(json.dumps(data))
    args = ["--openpose", *[f"{cam}={tmp_path / 'op' / cam}" for cam in CAMS], "--labelled", "all"]
    assert import_videos(import_recording, import_recording["root"] / "calibration.toml", tmp_path / "ds",
                         *args) == 0
    ds = validated(tmp_path / "ds")
    assert ds.keypoints == ["kp0", "kp1", "kp2"] and ds.units == "mm"
    expected = uv.copy()
    expected[7, :, 2] = np.nan
    ids = ds.frames("labelled")
    got, mask = ds.labels(ids)
    np.testing.assert_array_equal(mask, np.isfinite(expected[ids]).all(-1))
    np.testing.assert_allclose(got[mask], expected[ids][mask].astype(np.float32), atol=1e-5)


def test_import_mmpose_json(import_recording, tmp_path):
    uv = import_recording["uv"]
    args = ["--mmpose"]
    for c, cam in enumerate(CAMS):
        frames = []
        for f in range(N_FRAMES):
            ok = np.isfinite(uv[f, c]).all(-1)
            points = np.where(ok[:, None], uv[f, c], 0.0)
            frames.append({"frame_id": f + 1, "instances": [
                {"keypoints": points.tolist(), "keypoint_scores": np.where(ok, 0.8, 0.0).tolist(),
                 "bbox": [[0, 0, 10, 10]], "bbox_score": 0.9}]})
        path = tmp_path / f"results_{cam}.json"
        meta = {"dataset_name": "test", "keypoint_id2name": {str(k): n for k, n in enumerate(KEYPOINTS)}}
        path.write_text(json.dumps({"meta_info": meta, "instance_info": frames}))
        args.append(f"{cam}={path}")
    assert import_videos(import_recording, import_recording["root"] / "calibration.toml", tmp_path / "ds",
                         *args, "--labelled", "all", "--min-score", "0.5") == 0
    ds = validated(tmp_path / "ds")
    assert ds.keypoints == KEYPOINTS and ds.cameras == CAMS
    assert_labels(ds, import_recording)


# ------------------------------------------------------------------------------------------------------------
# Without labels; all or nothing; keypoint sets that differ


def test_import_without_labels(import_recording, tmp_path, capsys):
    calib = import_recording["root"] / "calibration.toml"
    assert import_videos(import_recording, calib, tmp_path / "x") == 1
    assert "no labels given: name the keypoints with --keypoints" in capsys.readouterr().err
    assert import_videos(import_recording, calib, tmp_path / "ds", "--keypoints", "head,body,tail",
                         "--stride", "3") == 0
    problems, ds = check_dataset(tmp_path / "ds")
    assert [(p.severity, p.file) for p in problems] == [("warning", "frames.csv")]
    assert "no labelled frames" in problems[0].message
    assert ds.keypoints == KEYPOINTS and ds.units == "mm"
    np.testing.assert_array_equal(ds.frames("unlabelled"), [0, 3, 6, 9])
    assert len(ds.frames("labelled")) == 0 and not (tmp_path / "ds" / "labels.csv").exists()


def test_failed_import_leaves_nothing_and_names_overwrite(import_recording, tmp_path, capsys):
    seqs = _sequences(import_recording, tmp_path / "seq")
    bad = tmp_path / "seq" / "east" / "img_0007.png"
    good = bad.read_bytes()
    bad.write_bytes(b"not a png")
    calib = import_recording["root"] / "calibration.toml"
    out = tmp_path / "ds"
    assert import_videos(import_recording, calib, out, "--keypoints", "head", videos=seqs) == 1
    err = capsys.readouterr().err
    assert "img_0007.png" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]  # no partial dataset, no temporary folder
    bad.write_bytes(good)
    assert import_videos(import_recording, calib, out, "--keypoints", "head", videos=seqs) == 0
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    assert import_videos(import_recording, calib, out, "--keypoints", "head", videos=seqs) == 1
    err = capsys.readouterr().err
    assert f"--out {out}: folder exists and is not empty; pass --overwrite to replace it" in err
    # A failing --overwrite keeps the old dataset whole.
    bad.write_bytes(b"not a png")
    assert import_videos(import_recording, calib, out, "--keypoints", "head", "--overwrite", videos=seqs) == 1
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    validated(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "seq"]


def test_dlc_keypoint_sets_that_differ_are_reported(import_recording, tmp_path, capsys):
    root = import_recording["root"]
    files = []
    for cam in CAMS:
        rows = (root / f"CollectedData_{cam}.csv").read_text().splitlines()
        if cam == "east":  # no 'tail' columns
            rows = [",".join(r.split(",")[:-2]) for r in rows]
        (tmp_path / f"{cam}.csv").write_text("\n".join(rows) + "\n")
        files.append(f"{cam}={tmp_path / cam}.csv")
    assert import_videos(import_recording, root / "calibration.toml", tmp_path / "ds", "--dlc", *files,
                         "--labelled", "all") == 0
    out = capsys.readouterr().out
    assert f"warning: camera east: keypoints tail have no labels in {tmp_path / 'east.csv'}" in out
    problems, ds = check_dataset(tmp_path / "ds")
    differ = [p for p in problems if "keypoint sets differ" in p.message]
    assert [(p.camera, p.severity) for p in differ] == [("east", "warning")]
    assert "tail" in differ[0].message
    assert not ds.labels(ds.frames("labelled"))[1][:, 1, 2].any()


def test_video_region_with_padding_moves_the_principal_point_out(import_recording):
    rig = recording_rig(import_recording)
    padded = rig.with_video_regions({"east": (0, -4, W_IMG, H_IMG + 4)})
    assert padded.size.tolist() == [[W_IMG, H_IMG], [W_IMG, H_IMG + 8], [W_IMG, H_IMG]]
    K, ref = padded.cameras.numpy()["K"], rig.cameras.numpy()["K"]
    np.testing.assert_allclose(K[1, 1, 2], ref[1, 1, 2] + 4)
    np.testing.assert_array_equal(K[[0, 2]], ref[[0, 2]])
    with pytest.raises(ValueError, match="whole-pixel size"):
        rig.with_video_regions({"east": (0, 0, 10.5, 10)})


def test_deepfly3d_no_estimate_marks_are_unlabelled_and_named(tmp_path, capsys):
    """Points DeepFly3D marks (0, 1) for "no estimate" (the top-right corner as fractions) are unlabelled, and
    the import says so, instead of dropping them as labels outside the images."""
    T = 3
    points = np.full((7, T, len(JOINTS), 2), 0.5)
    points[:, 1, :4] = (0.0, 1.0)
    points[:, 2, :2] = 0.0
    with open(tmp_path / "r.pkl", "wb") as f:
        pickle.dump({"points2d": points}, f)
    with showing_library_messages():  # the library logs its notes; the command line prints them
        tables = read_deepfly3d_pose(tmp_path / "r.pkl", {f"camera_{c}": (960, 480) for c in range(7)})
    idx = JOINTS.index("RF_body_coxa")  # seen by camera 0
    uv = tables["camera_0"].uv
    assert np.isnan(uv[1, idx]).all() and np.isnan(uv[2, idx]).all()
    np.testing.assert_allclose(uv[0, idx], [480.0, 240.0])
    out = capsys.readouterr().out
    assert (f"{7 * 6} of {points[..., 0].size} points2d hold (0, 0) or (0, 1), DeepFly3D's marks for a "
            "joint without an estimate: read as unlabelled") in out


def test_import_records_relative_sources_relative_to_the_dataset(import_recording, tmp_path, monkeypatch):
    """Paths given relative are written relative to the dataset folder: a dataset moved together with its
    recording still finds its calibration, videos and labels; absolute paths stay absolute."""
    import shutil

    from s3k.base.fileio import resolve_from
    from s3k.data import Dataset

    root = import_recording["root"]
    monkeypatch.chdir(root.parent)
    rel = root.name

    def run(folder, out):
        return main(["import", "--calibration", f"{folder}/calibration.toml",
                     "--videos", *[f"{c}={folder}/{c}.mkv" for c in CAMS], "--out", out,
                     "--sleap", *[f"{c}={folder}/{c}.analysis.h5" for c in CAMS]])

    assert run(rel, "project/ds") == 0
    source = json.loads((root.parent / "project/ds/s3k.json").read_text())["source"]
    assert source["calibration"] == f"../../{rel}/calibration.toml"
    assert source["videos"] == {c: f"../../{rel}/{c}.mkv" for c in CAMS}
    assert source["labels"] == {c: f"../../{rel}/{c}.analysis.h5" for c in CAMS}
    # moved together, elsewhere: the recorded paths still lead to the files
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    shutil.copytree(root.parent / "project", moved / "project")
    shutil.copytree(root, moved / rel)
    ds = Dataset.open(moved / "project/ds", cache="none")
    for value in [ds.source["calibration"], *ds.source["videos"].values(), *ds.source["labels"].values()]:
        found = resolve_from(ds.path, value).resolve()
        assert found.is_file() and moved / rel in found.parents
    # given absolute: recorded absolute
    assert run(str(root), "abs") == 0
    source = json.loads((root.parent / "abs/s3k.json").read_text())["source"]
    assert source["calibration"] == str(root / "calibration.toml")
    assert source["videos"] == {c: str(root / f"{c}.mkv") for c in CAMS}


# ------------------------------------------------------------------------------------------------------------
# Unsynchronized cameras: --frame-offsets


def test_frame_offsets_align_a_late_camera(import_recording, tmp_path, capsys):
    """Camera east's clock is 2 frames off: its frame i shows the others' frame i + 2 (its video and labels
    start 2 frames later). With --frame-offsets east=2 every dataset frame holds the same instant in every
    camera: the images and labels of the synchronized recording; frames 0-1, which east did not film, are
    left out."""

    from s3k.data.video import write_video

    root, late = import_recording["root"], tmp_path / "late"
    late.mkdir()
    n = 2
    write_video(late / "east.mkv", import_recording["frames"]["east"][n:], fps=30, codec="ffv1")
    write_sleap(late / "east.analysis.h5", import_recording["uv"][n:, 1, :, :, None], nodes=KEYPOINTS)
    videos = {cam: (late if cam == "east" else root) / f"{cam}.mkv" for cam in CAMS}
    labels = ["--sleap", *[f"{cam}={(late if cam == 'east' else root) / cam}.analysis.h5" for cam in CAMS]]
    args = [*labels, "--labelled", "all", "--frame-offsets", f"east={n}"]
    assert import_videos(import_recording, root / "calibration.toml", tmp_path / "ds", *args,
                         videos=videos) == 0
    ds = validated(tmp_path / "ds")
    ids = ds.frames()
    assert ids.min() == n and ids.max() == N_FRAMES - 1
    assert_labels(ds, import_recording)
    images = ds.images(ids)
    for c, cam in enumerate(CAMS):
        want = np.stack([import_recording["frames"][cam][f] for f in ids])
        np.testing.assert_array_equal(images[:, c], want, err_msg=cam)
    assert "frame_offsets" in (tmp_path / "ds" / "s3k.json").read_text()
    capsys.readouterr()
    assert import_videos(import_recording, root / "calibration.toml", tmp_path / "bad", *labels,
                         "--frame-offsets", "west=2", videos=videos) == 1
    assert "--frame-offsets 'west=2': unknown camera 'west' (cameras: north, east, south)" in \
        capsys.readouterr().err
