"""Calibration check on synthetic rigs: exact labels fit, a perturbed camera is named, noise is not."""

import cv2
import numpy as np
import pytest
import torch
from helpers.charuco import look_at, render_charuco_rig
from helpers.real_recording import REAL, needs_real

from s3k.geometry import Cameras
from s3k.geometry.consistency import check_calibration, leave_one_out_residuals, reprojection_residuals


def make_rig(C=4, seed=0):
    rng = np.random.default_rng(seed)
    Ks, dists, Rs, ts = [], [], [], []
    for c in range(C):
        angle = 2 * np.pi * c / C + rng.uniform(-0.2, 0.2)
        centre = np.array([np.cos(angle), np.sin(angle), rng.uniform(0.3, 0.8)]) * 1000.0  # millimetres
        R, t = look_at(centre)
        Ks.append([[600.0 + 20 * c, 0, 319.5], [0, 600.0 + 20 * c, 239.5], [0, 0, 1]])
        dists.append([-0.1 * (c % 2), 0.01, 0, 0, 0])
        Rs.append(R)
        ts.append(t)
    return [np.array(a) for a in (Ks, dists, Rs, ts)]


def observe(rig, B=30, Kp=5, noise=0.0, seed=1, drop=0.0):
    """Project random points near the origin with OpenCV; returns uv (B, C, K, 2) and mask (B, C, K)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-100, 100, (B * Kp, 3))
    uv = []
    for K, d, R, t in zip(*rig):
        p, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, d)
        uv.append(p.reshape(B, Kp, 2))
    uv = np.stack(uv, axis=1) + noise * rng.standard_normal((B, len(rig[0]), Kp, 2))
    mask = rng.uniform(size=uv.shape[:-1]) >= drop
    uv[~mask] = np.nan  # unlabelled entries may hold anything, NaN included
    return uv, mask


def cameras(rig, rotate=None, angle_deg=0.0):
    K, d, R, t = (a.copy() for a in rig)
    if rotate is not None:
        dR = cv2.Rodrigues(np.array([0.0, 1.0, 0.0]) * np.deg2rad(angle_deg))[0]
        centre = -R[rotate].T @ t[rotate]
        R[rotate] = dR @ R[rotate]  # the camera turned about its own y axis, its centre kept
        t[rotate] = -R[rotate] @ centre
    return Cameras.from_numpy(K, d, R, t, dtype=torch.float64)


NAMES = ["a", "b", "c", "d"]


def test_exact_labels_give_zero_residual():
    rig = make_rig()
    uv, mask = observe(rig, drop=0.2)
    res = reprojection_residuals(cameras(rig), uv, mask)
    loo = leave_one_out_residuals(cameras(rig), uv, mask)
    assert np.isnan(res[~mask]).all()
    assert np.nanmax(res) < 1e-6 and np.nanmax(loo) < 1e-6
    # LOO needs two other views: with 4 cameras and drops, some labelled entries have none.
    assert np.isfinite(loo[mask]).mean() > 0.5
    check = check_calibration(cameras(rig), uv, mask, NAMES)
    assert check.inconsistent == []


def test_noise_alone_flags_nothing():
    rig = make_rig()
    uv, mask = observe(rig, noise=1.0, drop=0.1)
    check = check_calibration(cameras(rig), uv, mask, NAMES)
    assert check.inconsistent == [], check.format()
    for row in check.cameras:
        assert 0.3 < row.median_px < 3 and row.loo_median_px >= row.median_px


@pytest.mark.parametrize("bad", [0, 2])
def test_perturbed_camera_is_named(bad):
    rig = make_rig()
    uv, mask = observe(rig, noise=1.0, drop=0.1)
    check = check_calibration(cameras(rig, rotate=bad, angle_deg=2.0), uv, mask, NAMES)
    assert check.inconsistent == [NAMES[bad]], check.format()
    text = check.format()
    assert f"INCONSISTENT: {NAMES[bad]}" in text
    # With the bad camera left out, the others fit as well as an unperturbed rig.
    good = check_calibration(cameras(rig), uv, mask, NAMES)
    for row, ref in zip(check.consistent, good.cameras):
        if row.name != NAMES[bad]:
            assert row.median_px == pytest.approx(ref.median_px, rel=0.5)
    bad_row = next(r for r in check.consistent if r.name == NAMES[bad])
    assert bad_row.median_px > 10 * good.cameras[bad].median_px


def test_copied_parameters_are_named():
    # The defect of a real recording: one camera carries another camera's parameters.
    rig = make_rig(C=5, seed=3)
    uv, mask = observe(rig, noise=0.5)
    K, d, R, t = (a.copy() for a in rig)
    K[1], d[1], R[1], t[1] = K[4], d[4], R[4], t[4]
    check = check_calibration(Cameras.from_numpy(K, d, R, t, dtype=torch.float64), uv, mask, list("abcde"))
    assert check.inconsistent == ["b"], check.format()


def test_three_cameras_gross_error():
    rig = [a[:3] for a in make_rig()]
    uv, mask = observe(rig, noise=0.5)
    assert check_calibration(cameras(rig), uv, mask, NAMES[:3]).inconsistent == []
    check = check_calibration(cameras(rig, rotate=1, angle_deg=10.0), uv, mask, NAMES[:3])
    assert check.inconsistent == ["b"], check.format()


def test_input_errors():
    rig = make_rig()
    uv, mask = observe(rig, B=3)
    with pytest.raises(ValueError, match="mask must have shape"):
        reprojection_residuals(cameras(rig), uv, mask[:, :2])
    with pytest.raises(ValueError, match=r"uv must have shape \(B, C, K, 2\)"):
        reprojection_residuals(cameras(rig), uv[0], mask[0])
    with pytest.raises(ValueError, match="3 cameras"):
        check_calibration(cameras(rig), uv, mask, NAMES[:3])


def _write_dataset(path, rig_written, rig_true, B=12):
    from s3k.data import DatasetWriter

    uv, mask = observe(rig_true, B=B, noise=0.5, drop=0.1)
    K, d, R, t = rig_written
    with DatasetWriter(path, [f"k{i}" for i in range(uv.shape[2])], NAMES, (640, 480), "mm",
                       calibration=(K, d, R, t)) as writer:
        for b in range(B):
            split = "labelled" if b % 2 else "test"
            images = np.zeros((4, 480, 640, 3), np.uint8)
            writer.add_frame(b, split, images, labels=(np.nan_to_num(uv[b]), mask[b]))
    return path


def test_cli_names_the_bad_camera(tmp_path, capsys):
    from s3k.cli import main

    rig = make_rig()
    good = _write_dataset(tmp_path / "good", rig, rig)
    assert main(["check-calibration", str(good)]) == 0
    assert "all cameras consistent" in capsys.readouterr().out
    bad = cameras(rig, rotate=3, angle_deg=2.0).numpy()
    path = _write_dataset(tmp_path / "bad", [bad[k] for k in ("K", "dist", "R", "t")], rig)
    assert main(["check-calibration", str(path), "--splits", "labelled"]) == 2
    out = capsys.readouterr().out
    assert "INCONSISTENT: d" in out and "6 frames (labelled)" in out
    assert main(["check-calibration", str(path), "--splits", "labeled"]) == 1
    assert "unknown split 'labeled'" in capsys.readouterr().err
    assert main(["check-calibration", str(tmp_path / "nothing")]) == 1
    assert "nothing" in capsys.readouterr().err


@pytest.fixture(scope="module")
def charuco_rig(tmp_path_factory):
    """A ChArUco board rendered in 8 poses for 3 cameras: ``(truth rig, spec, {camera: files})``."""
    return render_charuco_rig(tmp_path_factory.mktemp("charuco"))


def _copy_camera(rig, dst, src):
    """``rig`` with camera ``dst`` given the parameters of camera ``src`` (its distortion kept)."""
    a = rig.cameras.numpy()
    return rig.replace_camera(rig.names[dst], a["K"][src], a["dist"][dst], a["R"][src], a["t"][src])


def test_recalibrate_from_synthetic_charuco(charuco_rig):
    """A camera given another's parameters is recovered from rendered ChArUco views."""
    from s3k.rigcal.recalibration import detect_charuco, recalibrate_charuco

    truth, spec, files = charuco_rig
    names = truth.names
    detections = {n: detect_charuco(files[n], spec) for n in names}
    assert all(len(d) >= 6 for d in detections.values())
    broken = _copy_camera(truth, 1, 2)  # "q" carries the parameters of "r"
    fix = recalibrate_charuco(broken, "q", detections, spec, ["p", "r"])
    assert fix.pose_median_px < 0.5
    true = truth.cameras.numpy()
    np.testing.assert_allclose(fix.K, true["K"][1], rtol=0.005, atol=1e-9)
    assert abs(fix.dist[0]) < 0.02
    centre_true = -true["R"][1].T @ true["t"][1]
    centre_fit = -fix.R.T @ fix.t
    assert np.linalg.norm(centre_fit - centre_true) < 0.005 * np.linalg.norm(centre_true)
    angle = np.rad2deg(np.linalg.norm(cv2.Rodrigues(fix.R @ true["R"][1].T)[0]))
    assert angle < 0.2




@needs_real
def test_real_recording_names_side():
    """The sleap-anipose session's calibration gives camera "side" the parameters of "top"."""
    from s3k.data.formats.anipose import read_anipose_calibration
    from s3k.data.formats.sleap import read_sleap_analysis

    rig = read_anipose_calibration(REAL / "calibration.toml")
    uv = np.stack(
        [read_sleap_analysis(REAL / c / f"minimal_{c}_proofread.analysis.h5").uv for c in rig.names], axis=1
    )
    check = check_calibration(rig.cameras, uv, np.isfinite(uv).all(-1), rig.names, image_size=(1280, 1024))
    assert check.inconsistent == ["side"], check.format()
    assert "side and top have identical calibration parameters" in check.notes


def test_cli_recalibrate(charuco_rig, tmp_path, capsys):
    from s3k.cli import main
    from s3k.data import DatasetWriter
    from s3k.data.formats.anipose import read_anipose_calibration, write_anipose_calibration

    truth, spec, files = charuco_rig
    broken = _copy_camera(truth, 1, 2)
    write_anipose_calibration(tmp_path / "calibration.toml", broken)
    (tmp_path / "board.toml").write_text(
        f"board_x = {spec.squares_x}\nboard_y = {spec.squares_y}\nsquare_length = {spec.square_length}\n"
        f"marker_length = {spec.marker_length}\nmarker_bits = {spec.marker_bits}\n"
        f"dict_size = {spec.dict_size}\n"
    )
    t = truth.cameras.numpy()
    rig = [t["K"], t["dist"], t["R"], t["t"]]
    uv, mask = observe(rig, B=8, Kp=4, noise=0.3)
    with DatasetWriter(tmp_path / "ds", ["a", "b", "c", "d"], truth.names, (640, 480), "mm",
                       calibration=broken.cameras,
                       source={"calibration": str(tmp_path / "calibration.toml")}) as writer:
        for b in range(8):
            writer.add_frame(b, "labelled", np.zeros((3, 480, 640, 3), np.uint8),
                             labels=(np.nan_to_num(uv[b]), mask[b]))
    out = tmp_path / "fixed.toml"
    charuco = [f"{n}={files[n][0].parent}/{n}-*.png" for n in truth.names]
    code = main(["check-calibration", str(tmp_path / "ds"), "--recalibrate", "q", "--charuco", *charuco,
                 "--write-calibration", str(out)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "note: q and r have identical calibration parameters" in text
    assert "the test was incomplete" in text.split("recalibrated q")[0]
    assert "recalibrated q from 8 ChArUco frames" in text
    after = text.split("after recalibrating q:")[1]
    assert "all cameras consistent" in after
    fixed = read_anipose_calibration(out)
    K_fixed, K_true = fixed.cameras.numpy()["K"], truth.cameras.numpy()["K"]
    np.testing.assert_allclose(K_fixed[1], K_true[1], rtol=0.005, atol=1e-9)
    np.testing.assert_allclose(K_fixed[[0, 2]], K_true[[0, 2]])


def test_cli_without_labels_says_labels_are_needed(tmp_path, capsys):
    """A dataset of unlabelled frames only: the check fails with the reason, for every --splits."""
    from s3k.cli import main
    from s3k.data import DatasetWriter

    K, d, R, t = make_rig()
    with DatasetWriter(tmp_path / "ds", ["k0", "k1"], NAMES, (64, 48), "mm", calibration=(K, d, R, t)) as w:
        for b in range(3):
            w.add_frame(b, "unlabelled", np.zeros((4, 48, 64, 3), np.uint8))
    for extra in ([], ["--splits", "unlabelled"], ["--splits", "labelled,unlabelled,test"]):
        assert main(["check-calibration", str(tmp_path / "ds"), *extra]) == 1, extra
        err = capsys.readouterr().err
        assert "the dataset has no labelled or test frame with one: the check triangulates 2D labels" in err
        assert "import the recording with its labels" in err and "--splits" not in err
    # Labels there, but not in the splits chosen: the error names the splits that have them.
    labelled = _write_dataset(tmp_path / "labelled", make_rig(), make_rig())
    assert main(["check-calibration", str(labelled), "--splits", "unlabelled"]) == 1
    assert "no frames in unlabelled; the check triangulates 2D labels; use the labelled and test frames: " \
           "--splits labelled,test" in capsys.readouterr().err


def test_camera_without_labels_is_not_called_consistent(tmp_path, capsys):
    """A camera with no labels (its row all nan) cannot be judged: the report says so and does not call
    every camera consistent."""
    from s3k.cli import main

    rig = make_rig()
    uv, mask = observe(rig, B=20, noise=0.3)
    mask[:, 2] = False
    uv[:, 2] = np.nan
    check = check_calibration(cameras(rig), uv, mask, NAMES)
    text = check.format()
    assert check.unchecked == [NAMES[2]], text
    assert "all cameras consistent" not in text
    assert f"could not check camera(s) {NAMES[2]}: {NAMES[2]} has 0 leave-one-out residuals" in text

    from s3k.data import DatasetWriter

    K, d, R, t = rig
    with DatasetWriter(tmp_path / "ds", [f"k{i}" for i in range(uv.shape[2])], NAMES, (640, 480), "mm",
                       calibration=(K, d, R, t)) as writer:
        for b in range(len(uv)):
            writer.add_frame(b, "labelled", np.zeros((4, 480, 640, 3), np.uint8),
                             labels=(np.nan_to_num(uv[b]), mask[b]))
    assert main(["check-calibration", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr().out
    assert "all cameras consistent" not in out
    assert f"could not check camera(s) {NAMES[2]}" in out


def test_validate_fails_a_dataset_with_an_inconsistent_camera(tmp_path, capsys):
    """``s3k validate`` does not exit 0 with "OK" on a dataset whose camera the calibration check calls
    inconsistent: that camera would train on wrong targets."""
    from s3k.cli import main

    rig = make_rig()
    bad = cameras(rig, rotate=3, angle_deg=2.0).numpy()
    path = _write_dataset(tmp_path / "bad", [bad[k] for k in ("K", "dist", "R", "t")], rig)
    assert main(["validate", str(path), "--no-images"]) == 1
    out = capsys.readouterr().out
    assert "ERROR   calibration: camera(s) d disagree with the others' labels" in out
    assert "OK:" not in out and out.splitlines()[-1].startswith("UNUSABLE: 1 error(s)")
    good = _write_dataset(tmp_path / "good", rig, rig)
    assert main(["validate", str(good), "--no-images"]) == 0
