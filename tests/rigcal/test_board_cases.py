"""``s3k calibrate`` on the boards people have, drawn with OpenCV for three cameras p, q, r
(tests/helpers/charuco.py): a board printed inverted, a stray marker id in the background, a two-sided board
with its back face to one camera, a camera that sees the board in only a third of the frames. Each calibrates
in one command with every camera where it is, what detection took or dropped counted in the report; and the
report's held-out figures and warnings."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.charuco import render_charuco_rig

from s3k.base.errors import UserError
from s3k.cli import main
from s3k.data.formats.anipose import read_anipose_calibration
from s3k.rigcal.boards import Board, Faces, check_board_matches, detect_board

BOARD = ["--squares", "5x7", "--square-length", "30", "--marker-length", "22"]
CASES = {
    "inverted": {"inverted": True},
    "stray": {"stray": {"p": [3]}},
    "back": {"back": "r"},
    "third": {"seen": {"r": [0, 1, 2, 3]}},
}


@pytest.fixture(scope="module", params=list(CASES))
def case(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp(request.param)
    truth, spec, _ = render_charuco_rig(folder / "images", poses=12, **CASES[request.param])
    return request.param, folder, truth, spec


def _calibrate(folder, *extra):
    out = folder / "calibration.toml"
    args = [
        "calibrate",
        *[f"{n}={folder / 'images' / f'{n}-*.png'}" for n in "pqr"],
        *BOARD,
        "--out",
        str(out),
        "--overwrite",
        "--bootstrap",
        "2",
        *extra,
    ]
    return main(args), out


def _centres(rig):
    a = rig.cameras.numpy()
    C = np.stack([-R.T @ t for R, t in zip(a["R"], a["t"])])
    R0 = a["R"][0]
    return (C - C[0]) @ R0.T, a["R"] @ R0.T  # in the first camera's frame


def test_calibrates_in_one_command(case, capsys):
    """Every camera calibrated to its true place (the first camera's frame; 2 mm, 0.2 degree), and what
    detection took or dropped counted in the printed table and the saved report."""
    name, folder, truth, _ = case
    code, out = _calibrate(folder)
    text = capsys.readouterr().out
    assert code == 0, text
    got = read_anipose_calibration(out)
    assert got.names == ["p", "q", "r"]
    (c_got, r_got), (c_true, r_true) = _centres(got), _centres(truth)
    assert np.linalg.norm(c_got - c_true, axis=1).max() < 2.0
    for a, b in zip(r_got, r_true):
        assert np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1) / 2, -1, 1))) < 0.2
    report = json.loads((folder / "calibration.report.json").read_text())
    det = report["detections"]
    expected = {
        "inverted": ("inverted", {"p": 12, "q": 12, "r": 12}),
        "stray": ("stray_markers", {"p": 1, "q": 0, "r": 0}),
        "back": ("back_face", {"p": 0, "q": 0, "r": 12}),
        "third": ("board_frames", {"p": 12, "q": 12, "r": 4}),
    }[name]
    assert {n: det[n][expected[0]] for n in "pqr"} == expected[1]
    assert "stray ids" in text and "held out" in text and "square 30" in text
    if name == "stray":
        assert det["p"]["stray_ids"] == [40] and det["p"]["board_frames"] == 12
    if name == "third":  # r has no frame in the second half: not checked there, and said so
        assert report["halves"]["first_on_second_px"]["r"] is None
        assert any(
            "camera r saw the board in fewer than 3 frames of one half" in w for w in report["warnings"]
        )
    else:
        assert report["warnings"] == []
        held = report["halves"]["first_on_second_px"]
        assert all(0 < held[n] < 0.5 for n in "pqr")
    assert abs(report["square"]["all_frames_error"]) < 0.002


def test_inverted_only_and_one_sided(case, capsys):
    """--inverted looks for the inverted print alone; --one-sided leaves out the back face, and a camera that
    sees only the back is then refused naming the option that finds it."""
    name, folder, _, spec = case
    if name == "inverted":
        det = detect_board(folder / "images" / "p-*.png", spec, faces=Faces(normal=False))
        assert len(det.frames) == 12 and det.inverted == 12
        det = detect_board(folder / "images" / "p-*.png", spec, faces=Faces(inverted=False))
        with pytest.raises(UserError, match="no ArUco marker of the board's dictionary.*inverted"):
            check_board_matches("p", "x", det, spec)
    if name == "back":
        code, _ = _calibrate(folder, "--one-sided")
        err = capsys.readouterr().err.strip().splitlines()
        assert code != 0 and len(err) == 1
        assert "camera r" in err[0] and "back face" in err[0] and "--one-sided" in err[0]


def test_a_board_of_another_size_is_still_refused(tmp_path):
    """Ids beyond the board's in most images are a board of another size, not stray detections."""
    _, spec, _ = render_charuco_rig(tmp_path, poses=4)
    small = Board(5, 5, 30.0, 22.0, 4, 50)  # 12 markers; the 5 x 7 board has 17
    det = detect_board(tmp_path / "p-*.png", small)
    assert det.stray_frames == 4
    with pytest.raises(
        UserError,
        match=r"4 of the 4 images showing ArUco markers show ids beyond the board's "
        r"0-11 \(up to 16\).*smaller than the one filmed.*--squares",
    ):
        check_board_matches("p", "x", det, small)


def test_a_camera_knocked_halfway_is_warned_of(tmp_path, capsys):
    """A camera turned by 1 degree halfway through the board frames: each half fits on its own, but the rig of
    one half puts the other half's corners pixels off in that camera and the halves' rigs disagree on it; the
    report warns, naming it."""
    render_charuco_rig(tmp_path / "images", poses=12, turned="q")
    code, _ = _calibrate(tmp_path)
    text = capsys.readouterr().out
    assert code == 0
    report = json.loads((tmp_path / "calibration.report.json").read_text())
    held = report["halves"]["first_on_second_px"]
    assert held["q"] > 1.0 and held["p"] < held["q"] and held["r"] < held["q"]
    assert report["halves"]["rigs_apart"]["q"]["orientation_deg"] > 0.5
    assert "warning: camera q: the rig fitted on one half of the board frames puts the other half" in text


def test_low_coverage_and_a_wrong_square_are_warned_of():
    """The warnings' thresholds: coverage below 25%, a triangulated square 0.5% off its known side."""
    from s3k.rigcal.report import _warnings

    figures = {
        "detections": {"p": {}},
        "halves": {
            "first_on_second_px": {"p": 0.2},
            "second_on_first_px": {"p": 0.3},
            "rigs_apart": {"p": {"centre_mm": 0.0}},
            "scale_difference": 0.001,
            "first": "0-5",
            "second": "6-11",
        },
        "square": {"known": 24.0, "all_frames_error": 0.001, "held_out_error": -0.02},
        "coverage": {"p": 0.2},
    }
    warnings = _warnings(figures, "mm")
    assert len(warnings) == 2
    assert "square measures 0.98 times its known 24 mm (held out; -2.00%" in warnings[0]
    assert "camera p: the board covered 20% of its image" in warnings[1]
    figures["coverage"]["p"], figures["square"]["held_out_error"] = 0.3, 0.004
    assert _warnings(figures, "mm") == []


def test_a_camera_out_of_sync_is_found_and_its_offset_reported(tmp_path, capsys):
    """The board moving smoothly, camera q's images one frame ahead of p's and r's two behind: the report
    gives each camera's offset against p from the board's motion (0 for all when in sync) and what to cut."""
    render_charuco_rig(tmp_path / "images", poses=16, lag={"q": -1, "r": 2})
    code, _ = _calibrate(tmp_path)
    text = capsys.readouterr().out
    assert code == 0
    offsets = json.loads((tmp_path / "calibration.report.json").read_text())["frame_offsets"]
    # the convention of s3k import --frame-offsets: the camera's frame i shows p's frame i + N
    assert {n: o["offset"] for n, o in offsets.items()} == {"p": 0, "q": 1, "r": -2}
    assert offsets["r"]["px"] < 2.0 < 10.0 < offsets["r"]["px_at_0"]
    assert "camera r: its frame i shows the first camera's frame i-2 " in text
    assert "cut 2 frame(s) from the start of camera r's video" in text
    render_charuco_rig(tmp_path / "synced" / "images", poses=16, lag={})
    code, _ = _calibrate(tmp_path / "synced", "--report", str(tmp_path / "synced.json"))
    assert code == 0 and "its frame i shows" not in capsys.readouterr().out
    offsets = json.loads((tmp_path / "synced.json").read_text())["frame_offsets"]
    assert {n: o["offset"] for n, o in offsets.items()} == {"p": 0, "q": 0, "r": 0}
