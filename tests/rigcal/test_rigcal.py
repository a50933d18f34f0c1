"""s3k calibrate on a simulated rig: a ChArUco board rendered by MuJoCo into three cameras with known
intrinsics and poses; the rig recovered from the frames alone; the one-line errors for a camera that shares no
board view and for a board smaller than the one filmed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from s3k.base.errors import UserError
from s3k.cli import main as cli_main

pytest.importorskip("mujoco")
pytest.importorskip("scipy")

from s3k.rigcal.boards import Board, check_board_matches, detect_board  # noqa: E402
from s3k.rigcal.rig import calibrate_detections  # noqa: E402
from s3k.sim.board_rig import render_board_rig  # noqa: E402

BOARD = Board(7, 5, 40.0, 30.0, 4, 50)  # ChArUco, 40 mm squares: the calibration's unit is mm


@pytest.fixture(scope="module")
def sim_rig(tmp_path_factory):
    root = tmp_path_factory.mktemp("boardrig")
    rig = render_board_rig(root / "frames", BOARD, metres_per_unit=0.001, cameras=3, size=(640, 512),
                           poses=16, seed=0)
    detections = [detect_board(rig.folders[n], BOARD) for n in rig.names]
    return root, rig, detections


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_recovers_the_simulated_rig(sim_rig):
    """Focal lengths within 0.5%, camera centres within 2 mm and orientations within 0.2 degree of the truth
    (world = the first camera, unit = the board's mm)."""
    _, rig, detections = sim_rig
    cal = calibrate_detections(rig.names, detections, BOARD)
    a = cal.adjusted
    R0, t0 = rig.R[0], rig.t[0] * 1000.0  # truth in mm, expressed in the first camera's frame
    for c in range(len(rig.names)):
        R_true = rig.R[c] @ R0.T
        t_true = rig.t[c] * 1000.0 - R_true @ t0
        assert abs(a.intrinsics[c].f / rig.K[c, 0, 0] - 1) < 0.005
        assert np.linalg.norm(-R_true.T @ t_true - (-a.R[c].T @ a.t[c])) < 2.0
        assert _angle_deg(a.R[c] @ R_true.T) < 0.2
    assert all(r.median_px < 0.5 and r.views >= 8 for r in cal.report)
    assert all(0 < r.coverage <= 1 for r in cal.report)


def test_calibrate_command_writes_anipose_toml(sim_rig, tmp_path, capsys):
    """The command prints the per-camera table and writes a calibration.toml and a picture that s3k's
    anipose reader reads back (mm from the board's square length)."""
    from s3k.data.formats.anipose import read_anipose_calibration

    _, rig, _ = sim_rig
    out, fig = tmp_path / "calibration.toml", tmp_path / "calibration.png"
    args = ["calibrate", *[f"{n}={rig.folders[n]}" for n in rig.names], "--squares", "7x5",
            "--square-length", "40", "--marker-length", "30", "--dict", "4x4_50", "--out", str(out),
            "--figure", str(fig)]
    assert cli_main(args) == 0
    text = capsys.readouterr().out
    assert "median px" in text and "coverage" in text and all(n in text for n in rig.names)
    back = read_anipose_calibration(out)
    assert back.names == rig.names and back.units == "mm"
    assert np.allclose(back.cameras.numpy()["K"][:, 0, 0], rig.K[:, 0, 0], rtol=0.005)
    assert fig.stat().st_size > 10_000


def test_camera_sharing_no_board_view_is_named(sim_rig):
    _, rig, detections = sim_rig
    apart = replace(detections[2], frames={k + 1000: v for k, v in detections[2].frames.items()})
    with pytest.raises(UserError, match=r"camera cam2 shares no board view with the others"):
        calibrate_detections(rig.names, [detections[0], detections[1], apart], BOARD)


def test_board_size_not_matching_the_detections(sim_rig):
    _, rig, _ = sim_rig
    small = Board(5, 5, 40.0, 30.0, 4, 50)  # 12 markers; the frames show ids up to 16
    det = detect_board(rig.folders["cam0"], small)
    with pytest.raises(UserError, match=r"cam0 .*ids beyond the board's 0-11 \(up to 1[0-9]\).*smaller"):
        check_board_matches("cam0", rig.folders["cam0"], det, small)


def test_calibrate_command_one_line_errors(sim_rig, tmp_path, capsys):
    _, rig, _ = sim_rig
    out = str(tmp_path / "c.toml")
    assert cli_main(["calibrate", f"cam0={rig.folders['cam0']}", "--out", out]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no board given" in err[0] and "--board" in err[0]
    assert cli_main(["calibrate", f"cam0={tmp_path / 'missing.mp4'}", "--squares", "7x5", "--square-length",
                     "40", "--out", out]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.mp4" in err[0]


def test_recovers_the_rig_from_a_checkerboard(tmp_path):
    """A plain checkerboard (7 x 6 squares: odd in all, so not symmetric under a half turn): OpenCV reads its
    grid from either end, the dark first square orders it, wrong reads are left out; same tolerances."""
    board = Board(7, 6, 40.0)
    rig = render_board_rig(tmp_path, board, cameras=3, size=(640, 512), poses=16, seed=0)
    cal = calibrate_detections(rig.names, [detect_board(rig.folders[n], board) for n in rig.names], board)
    a = cal.adjusted
    R0, t0 = rig.R[0], rig.t[0] * 1000.0
    for c in range(3):
        R_true = rig.R[c] @ R0.T
        t_true = rig.t[c] * 1000.0 - R_true @ t0
        assert abs(a.intrinsics[c].f / rig.K[c, 0, 0] - 1) < 0.005
        assert np.linalg.norm(-R_true.T @ t_true - (-a.R[c].T @ a.t[c])) < 2.0
        assert _angle_deg(a.R[c] @ R_true.T) < 0.2
    with pytest.raises(UserError, match="looks the same turned by 180 degrees"):
        check_board_matches("cam0", "x", cal.detections[0], Board(7, 5, 40.0))


def test_origin_view_and_extra_points(sim_rig):
    """--origin-view puts the world on the board of that frame (the rig's shape unchanged); extra points seen
    by several cameras (labels) join the adjustment and fit to their noise."""
    from s3k.rigcal.rig import refine_with_points

    _, rig, detections = sim_rig
    cal = calibrate_detections(rig.names, detections, BOARD)
    key = cal.view_keys[3]
    moved = calibrate_detections(rig.names, detections, BOARD, origin_view=key)
    Rv, tv = moved.adjusted.views[3]
    assert np.allclose(Rv, np.eye(3), atol=1e-9) and np.allclose(tv, 0, atol=1e-6)
    centres = [np.stack([-R.T @ t for R, t in zip(c.adjusted.R, c.adjusted.t)]) for c in (cal, moved)]
    assert np.allclose(np.linalg.norm(centres[0][1:] - centres[0][0], axis=1),
                       np.linalg.norm(centres[1][1:] - centres[1][0], axis=1), atol=1e-6)
    # 30 points near where the cameras look (the true world, mm), projected with the truth plus 0.3 px noise
    rng = np.random.default_rng(0)
    X = rng.uniform(-60, 60, (30, 3))
    uv = np.full((1, 3, 30, 2), np.nan)
    for c in range(3):
        xc = X @ rig.R[c].T + rig.t[c] * 1000.0
        uv[0, c] = xc[:, :2] / xc[:, 2:] * rig.K[c, 0, 0] + rig.K[c, :2, 2] + rng.normal(0, 0.3, (30, 2))
    refined = refine_with_points(cal, uv)
    assert len(refined.adjusted.points) == 30
    assert np.median(np.linalg.norm(refined.adjusted.point_residuals, axis=1)) < 1.0
    for c in range(3):
        assert abs(refined.adjusted.intrinsics[c].f / rig.K[c, 0, 0] - 1) < 0.005
