"""``s3k import`` of recordings laid out as other tools write them, where a first try used to fail: DeepFly3D
results in pixels, videos padded by their encoder, a format's visibility rule, small SLEAP projects.

Every file is written here in the format's published layout, for the 3-camera recording of
``helpers.recordings`` (the ``import_recording`` fixture)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from helpers.recordings import (
    CAMS,
    H_IMG,
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

from s3k.data.formats.deepfly3d import points2d_layout

# ------------------------------------------------------------------------------------------------------------
# DeepFly3D results: (row, column) fractions or (x, y) pixels


def _df3d_result(import_recording, tmp_path, points2d, **extra):
    result = {**df3d_calib(recording_rig(import_recording)), "points2d": np.nan_to_num(points2d),
              "camera_ordering": np.arange(3), **extra}
    path = tmp_path / "df3d_result.pkl"
    with open(path, "wb") as f:
        pickle.dump(result, f)
    return path


def _df3d_import(import_recording, tmp_path, path, *extra):
    videos = {f"camera_{c}": import_recording["root"] / f"{cam}.mkv" for c, cam in enumerate(CAMS)}
    return import_videos(import_recording, path, tmp_path / "ds", "--deepfly3d", str(path), "--units", "mm",
                         *extra, videos=videos)


def test_deepfly3d_pixel_points_land_on_their_image_points(import_recording, tmp_path, capsys):
    """DeepFly3D's shipped results hold (x, y) pixels: every label lands where it was, none is dropped."""
    xy = import_recording["uv"].transpose(1, 0, 2, 3)  # (C, T, J, 2) as (x, y) pixels
    path = _df3d_result(import_recording, tmp_path, xy)
    assert _df3d_import(import_recording, tmp_path, path, "--labelled", "all") == 0
    out = capsys.readouterr().out
    assert "points2d read as (x, y) pixels" in out and "fall outside" not in out
    ds = validated(tmp_path / "ds")
    assert len(ds.frames("labelled")) == N_FRAMES
    assert_labels(ds, import_recording, atol=1e-4)


def test_deepfly3d_layout_from_the_reprojection_of_its_3d_points(import_recording, tmp_path, capsys):
    """With the file's 3D points the calibration decides, also for (row, column) pixels that the values alone
    would take for (x, y)."""
    rc = import_recording["uv"].transpose(1, 0, 2, 3)[..., ::-1]
    X = import_recording["X"]  # points3d: aligned to a template, not in the cameras' frame
    path = _df3d_result(import_recording, tmp_path, rc, points3d_wo_procrustes=X, points3d=X * 0.01)
    assert _df3d_import(import_recording, tmp_path, path, "--labelled", "all") == 0
    out = capsys.readouterr().out
    assert "points2d read as (row, column) pixels: they lie 0.0 px (median) from the reprojection" in out
    assert_labels(validated(tmp_path / "ds"), import_recording, atol=1e-4)


def test_deepfly3d_layout_from_the_values():
    sizes = {"camera_0": (960, 480), "camera_1": (960, 480)}
    points = np.zeros((2, 3, 4, 2))
    points[..., 0], points[..., 1] = 0.25, 0.75  # fractions; zeros are DeepFly3D's "no estimate"
    points[0, 0, 0] = 0
    assert points2d_layout(points, sizes)[0] == "fractions"
    points[..., 0], points[..., 1] = 700.0, 300.0  # x beyond the height: (x, y)
    assert points2d_layout(points, sizes)[0] == "xy"
    points[..., 0], points[..., 1] = 300.0, 700.0  # the same point as (row, column)
    assert points2d_layout(points, sizes)[0] == "rc"


def test_labels_dropped_en_masse_say_why(import_recording, tmp_path, capsys):
    """Labels far outside the images are dropped, and the error says that, not that --labelled is too many."""
    path = _df3d_result(import_recording, tmp_path,
                        import_recording["uv"].transpose(1, 0, 2, 3) * 1000 + 5000)
    assert _df3d_import(import_recording, tmp_path, path) == 1
    err = capsys.readouterr().err
    assert "labels fall outside the (cropped) images and are dropped (e.g. camera camera_0 frame 0 joint_0 " \
           "at x " in err and f"in {W_IMG}x{H_IMG})" in err
    assert "0 frames keep a keypoint labelled in >= 2 cameras" in err and "--labelled" not in err
    assert "not in the videos' pixels" in err


def test_deepfly3d_visibility_rule_is_one_line_not_pages(import_recording, tmp_path, capsys):
    """DeepFly3D's 7 cameras each see 14 to 19 of the 38 joints by its documented rule: the import says so
    once instead of warning per camera about the joints of the far side."""
    import cv2

    from s3k.data.formats.deepfly3d import JOINTS, camera_sees_joint

    calib = df3d_calib(recording_rig(import_recording))
    seven = {c: calib[c % 3] for c in range(7)}
    X = np.random.default_rng(1).uniform(-40, 40, (N_FRAMES, len(JOINTS), 3))
    points2d = np.stack([cv2.projectPoints(X.reshape(-1, 3), cv2.Rodrigues(cam["R"])[0], cam["tvec"],
                                           cam["intr"], None)[0].reshape(N_FRAMES, len(JOINTS), 2)
                         for cam in seven.values()])
    path = tmp_path / "df3d_result.pkl"
    with open(path, "wb") as f:
        pickle.dump({**seven, "points2d": points2d}, f)
    videos = {f"camera_{c}": import_recording["root"] / f"{CAMS[c % 3]}.mkv" for c in range(7)}
    assert import_videos(import_recording, path, tmp_path / "ds", "--deepfly3d", str(path), "--units", "mm",
                         "--labelled", "all", videos=videos) == 0
    captured = capsys.readouterr()
    lines = (captured.out + captured.err).splitlines()
    assert [line for line in lines if "visibility rule" in line] == [
        "note: DeepFly3D's visibility rule leaves 19 to 24 of the 38 joints unlabelled in each camera: "
        "those of the fly's far side (docs/importing.md#what-happens-to-each-format)"]
    # no warning per camera for the joints the rule leaves out (other warnings, e.g. no test frames, may come)
    assert not [line for line in lines if line.startswith("warning:") and "have no labels" in line], lines
    ds = validated(tmp_path / "ds")
    uv, mask = ds.labels(ds.frames("labelled"))
    for c in range(7):
        seen = [camera_sees_joint(c, j) for j in range(len(JOINTS))]
        np.testing.assert_array_equal(mask[:, c], np.broadcast_to(seen, mask[:, c].shape))


# ------------------------------------------------------------------------------------------------------------
# A small SLEAP project: its defaults take what is there


def test_small_sleap_project_imports_with_the_defaults(import_recording, tmp_path, capsys):
    """Two tracks and four labelled frames: without --sleap-track, --labelled or --test the import takes the
    most labelled track and labels every frame it has, and says both."""

    uv = import_recording["uv"]
    files = []
    for c, cam in enumerate(CAMS):
        loc = np.full((N_FRAMES, 3, 2, 2), np.nan)  # (frames, nodes, xy, tracks)
        loc[:4, :, :, 0] = uv[:4, c]  # "mouse": frames 0-3
        loc[6, :, :, 1] = uv[6, c] + 1  # "shadow": frame 6
        write_sleap(tmp_path / f"{cam}.analysis.h5", loc, names=["mouse", "shadow"])
        files.append(f"{cam}={tmp_path / cam}.analysis.h5")
    assert import_videos(import_recording, import_recording["root"] / "calibration.toml", tmp_path / "ds",
                         "--sleap", *files) == 0
    out = capsys.readouterr().out
    assert "note: 2 tracks are labelled (frames: mouse 12, shadow 3); importing mouse, the most" in out
    assert ("note: 4 frames have a keypoint labelled in >= 2 cameras: 4 labelled, 0 test (--labelled N and "
            "--test N choose)") in out
    ds = validated(tmp_path / "ds")
    np.testing.assert_array_equal(ds.frames("labelled"), [0, 1, 2, 3])
    assert_labels(ds, import_recording)


# ------------------------------------------------------------------------------------------------------------
# Videos padded or cropped by their encoder


@pytest.mark.parametrize("change", ["narrower", "taller"])
def test_padded_videos_import_with_the_option_the_error_names(import_recording, tmp_path, capsys, change):
    """Two cameras' videos 4 columns narrower than calibrated (the encoder cut its padding), or one video 4
    rows taller (padding added at the bottom): the first error names the exact option, and that option alone
    imports them; the images differ in size by those pixels, so the smaller are padded to the largest."""
    import re

    from s3k.data.video import write_video

    videos = {cam: import_recording["root"] / f"{cam}.mkv" for cam in CAMS}
    changed = ["north", "east"] if change == "narrower" else ["south"]
    for cam in changed:
        videos[cam] = tmp_path / f"{cam}.mkv"
        frames = import_recording["frames"][cam]
        if change == "narrower":
            frames = [f[:, :-4] for f in frames]
        else:
            frames = [np.concatenate([f, np.zeros((4, W_IMG, 3), np.uint8)]) for f in frames]
        write_video(videos[cam], frames, codec="ffv1")
    calib = import_recording["root"] / "calibration.toml"
    sleap = ["--sleap", *[f"{cam}={import_recording['root'] / cam}.analysis.h5" for cam in CAMS]]
    assert import_videos(import_recording, calib, tmp_path / "x", *sleap, videos=videos) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    option = re.search(r"pass (--video-region [^(]*) \(other placements", err)
    assert option, err
    assert import_videos(import_recording, calib, tmp_path / "ds", *sleap, *option.group(1).split(),
                         "--labelled", "all", videos=videos) == 0
    out = capsys.readouterr().out
    W, H = (W_IMG, H_IMG) if change == "narrower" else (W_IMG, H_IMG + 4)
    padded = ", ".join(cam for cam in CAMS if (cam in changed) == (change == "narrower"))
    assert f"note: the images of {padded} are padded with black at the right and bottom to {W}x{H}" in out
    ds = validated(tmp_path / "ds")
    assert ds.image_size == (W, H) and len(ds.frames("labelled")) == N_FRAMES
    # cut or added at the right and bottom: K is unchanged
    assert_same_cameras(ds, recording_rig(import_recording))
    assert_labels(ds, import_recording)
    images = ds.images([3])[0]
    for c, cam in enumerate(CAMS):
        original = import_recording["frames"][cam][3]
        if change == "narrower" and cam in changed:
            np.testing.assert_array_equal(images[c][:, :-4], original[:, :-4])
            assert not images[c][:, -4:].any()
        elif change == "taller" and cam not in changed:
            np.testing.assert_array_equal(images[c][:-4], original)
            assert not images[c][-4:].any()
        else:
            np.testing.assert_array_equal(images[c][:H_IMG], original)
