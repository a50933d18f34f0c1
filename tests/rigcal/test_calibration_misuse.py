"""What a careless or hostile user may give ``s3k calibrate`` and ``s3k check-calibration``: boards out of
range, camera names that are paths, outputs over the command's own inputs, a repair that is worse than the
calibration, the same images for several cameras. Each is refused in one line before any work, and nothing
is half-written. The board is drawn with OpenCV (tests/helpers/charuco.py): a few seconds in all."""

from __future__ import annotations

import errno
import pathlib
import re
import shutil

import numpy as np
import pytest
from helpers.charuco import write_recalibration_case

from s3k.base.errors import UserError
from s3k.cli import main
from s3k.data.formats.anipose import read_anipose_calibration, write_anipose_calibration
from s3k.rigcal.boards import read_board_toml

BOARD = ["--squares", "5x7", "--square-length", "30", "--marker-length", "22"]


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A good calibration of cameras p, q, r, their board images and a labelled dataset of the rig."""
    folder = tmp_path_factory.mktemp("misuse")
    truth, spec, files = write_recalibration_case(folder, broken=False)
    return folder, truth, files


def _sources(case, **given):
    folder, truth, _ = case
    return [f"{n}={given.get(n, folder / 'images' / f'{n}-*.png')}" for n in truth.names]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


# ------------------------------------------------------------------------------------------------------------
# the board: one check where it is read, for both commands

BAD_BOARDS = [
    ("board_x = 0\nboard_y = 0", r"board_x must be a whole number from 2 to 100, got 0"),
    ("board_x = 99999\nboard_y = 99999", r"board_x must be a whole number from 2 to 100, got 99999"),
    ("board_x = nan\nboard_y = 7", r"board_x must be a whole number from 2 to 100, got nan"),
    ('board_x = "eight"\nboard_y = 7', r"board_x must be a whole number from 2 to 100, got 'eight'"),
    ("board_x = 5\nboard_y = 7.5", r"board_y must be a whole number from 2 to 100, got 7.5"),
]
BAD_LENGTHS = [
    ("square_length = 30\nmarker_length = 40", r"marker_length must be a length from 0 up to .* 30, got 40"),
    ("square_length = -30\nmarker_length = 22", r"square_length must be a finite length above 0, got -30"),
    ("square_length = inf\nmarker_length = 22", r"square_length must be a finite length above 0, got inf"),
    ("square_length = 30\nmarker_length = 22\ndict_size = 60",
     r"dict_size must be one of 50, 100, 250, 1000"),
]


def _board_file(path: pathlib.Path, text: str) -> pathlib.Path:
    fields = dict(line.split(" = ") for line in text.splitlines())
    base = {"board_x": "5", "board_y": "7", "square_length": "30", "marker_length": "22"}
    path.write_text("".join(f"{k} = {v}\n" for k, v in {**base, **fields}.items()))
    return path


@pytest.mark.parametrize("text, message", BAD_BOARDS + BAD_LENGTHS)
def test_board_file_out_of_range_is_named(tmp_path, text, message):
    with pytest.raises(UserError, match=message):
        read_board_toml(_board_file(tmp_path / "board.toml", text))


def test_board_with_more_markers_than_its_dictionary(tmp_path):
    with pytest.raises(UserError, match=r"20x20 squares has 200 markers, more than the 50 of its dictionary"):
        read_board_toml(_board_file(tmp_path / "board.toml", "board_x = 20\nboard_y = 20"))


@pytest.mark.parametrize("squares, length, marker, message", [
    ("0x0", "30", "22", r"--squares 0x0: squares along x must be a whole number from 2 to 100, got 0"),
    ("99999x99999", "30", "22", r"--squares 99999x99999: squares along x .* got 99999"),
    ("eightx7", "30", "22", r"--squares eightx7: squares along x .* got 'eight'"),
    ("5x7", "30", "40", r"--marker-length must be a length from 0 up to .* 30, got 40"),
])
def test_calibrate_board_options_out_of_range(case, tmp_path, capsys, squares, length, marker, message):
    args = ["calibrate", *_sources(case), "--squares", squares, "--square-length", length, "--marker-length",
            marker, "--out", str(tmp_path / "c.toml")]
    assert main(args) == 1
    assert re.search(message, _one_line(capsys))
    assert not (tmp_path / "c.toml").exists()


@pytest.mark.parametrize("text, message", BAD_BOARDS[:4] + BAD_LENGTHS[:3])
def test_check_calibration_board_out_of_range(case, tmp_path, capsys, text, message):
    folder, truth, _ = case
    board = _board_file(tmp_path / "board.toml", text)
    charuco = [f"{n}={folder / 'images'}/{n}-*.png" for n in truth.names]
    assert main(["check-calibration", str(folder / "ds"), "--recalibrate", "q", "--board", str(board),
                 "--charuco", *charuco]) == 1
    assert re.search(message, _one_line(capsys))


def test_board_with_x_and_y_swapped_in_recalibrate(case, tmp_path, capsys):
    """calibrate and check-calibration --recalibrate both name the board's size as the likely mistake."""
    folder, truth, _ = case
    board = _board_file(tmp_path / "board.toml", "board_x = 7\nboard_y = 5")
    charuco = [f"{n}={folder / 'images'}/{n}-*.png" for n in truth.names]
    assert main(["check-calibration", str(folder / "ds"), "--recalibrate", "q", "--board", str(board),
                 "--charuco", *charuco]) == 1
    line = _one_line(capsys)
    assert "ArUco markers 0-16 but no ChArUco corners" in line and "check the board's size" in line


# ------------------------------------------------------------------------------------------------------------
# camera names


@pytest.mark.parametrize("name", ["../escape", "a/b", "a\\b", "..", ".", "", "two\nlines", "tab\there",
                                  "nul\0"])
def test_camera_names_that_are_not_file_names(name):
    from s3k.data.rig import check_camera_name

    with pytest.raises(UserError, match="camera|name"):
        check_camera_name(name, "here")


def test_camera_names_that_are_file_names():
    from s3k.data.rig import check_camera_name

    for name in ("top", "cam 1", "Kamera-ü", "a..b", ".hidden"):
        assert check_camera_name(name, "here") == name


@pytest.mark.parametrize("name, shown", [("../escape", r"'/'"), ("a\nb", r"'\\n'")])
def test_calibration_toml_with_a_path_as_camera_name(case, tmp_path, name, shown):
    folder, truth, _ = case
    text = (folder / "calibration.toml").read_text()
    toml_name = name.replace("\n", "\\n")
    (tmp_path / "c.toml").write_text(text.replace('name = "p"', f'name = "{toml_name}"'))
    with pytest.raises(UserError, match=rf"c.toml: \[cam_0\] name: camera name .* holds {shown}"):
        read_anipose_calibration(tmp_path / "c.toml")


@pytest.mark.parametrize("name", ["../escape", "a\nb"])
def test_calibrate_refuses_a_path_as_camera_name(case, tmp_path, capsys, name):
    folder, truth, _ = case
    args = ["calibrate", f"{name}={folder / 'images'}/p-*.png", *_sources(case)[1:], *BOARD,
            "--out", str(tmp_path / "c.toml")]
    assert main(args) == 1
    assert "camera name" in _one_line(capsys)
    assert not list(tmp_path.iterdir())


def test_import_refuses_a_path_as_camera_name(case, tmp_path, capsys):
    """The calibration and the videos agree on the name: still refused, nothing written."""
    folder, _, _ = case
    text = (folder / "calibration.toml").read_text().replace('name = "p"', 'name = "../escape"')
    (tmp_path / "c.toml").write_text(text)
    assert main(["import", "--calibration", str(tmp_path / "c.toml"), "--videos",
                 f"../escape={folder / 'images'}/p-*.png", "--keypoints", "a", "--out",
                 str(tmp_path / "ds")]) == 1
    assert "camera name '../escape' holds '/'" in _one_line(capsys)
    assert not (tmp_path / "ds").exists()


def test_overlay_files_stay_in_their_folder(tmp_path):
    from s3k.inference.track import overlay_file

    assert overlay_file(tmp_path / "o", "top") == tmp_path / "o" / "top.mp4"
    for name in ("../escape", "..", "a/b"):
        with pytest.raises(UserError, match="camera"):
            overlay_file(tmp_path / "o", name)


def test_writer_refuses_a_path_as_camera_name(case, tmp_path):
    _, truth, _ = case
    bad = truth.select(truth.names)
    bad.names[0] = "../escape"
    with pytest.raises(UserError, match="camera name '../escape'"):
        write_anipose_calibration(tmp_path / "c.toml", bad)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------------------------------
# the calibration's writer: atomic, never over an input


def test_writer_stopped_midway_leaves_the_old_calibration_whole(case, tmp_path, monkeypatch):
    folder, truth, _ = case
    target = tmp_path / "calibration.toml"
    shutil.copy(folder / "calibration.toml", target)
    before = target.read_bytes()

    def disk_full(self, data, *args, **kwargs):
        with open(self, "wb" if isinstance(data, bytes) else "w") as f:
            f.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pathlib.Path, "write_bytes", disk_full)
    monkeypatch.setattr(pathlib.Path, "write_text", disk_full)
    with pytest.raises(OSError, match="No space left"):
        write_anipose_calibration(target, truth)
    monkeypatch.undo()
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.toml"]
    assert read_anipose_calibration(target).names == truth.names


def test_calibrate_out_on_its_own_inputs(case, tmp_path, capsys):
    folder, _, files = case
    image = tmp_path / "p-3.png"
    shutil.copy(files["p"][3], image)
    sources = _sources(case, p=tmp_path / "p-*.png")
    for out, given in ((image, "CAM=SOURCE"), (folder / "board.toml", "--labels")):
        before = out.read_bytes()
        extra = ["--labels", f"p={out}"] if given == "--labels" else []
        assert main(["calibrate", *sources, *BOARD, "--out", str(out), "--overwrite", *extra]) == 1
        line = _one_line(capsys)
        assert f"is this command's input ({given}" in line and "--out" in line
        assert out.read_bytes() == before


def test_write_calibration_on_the_board_or_its_images(case, tmp_path, capsys):
    folder, truth, files = case
    board = tmp_path / "board.toml"
    shutil.copy(folder / "board.toml", board)
    charuco = [f"{n}={folder / 'images'}/{n}-*.png" for n in truth.names]
    base = ["check-calibration", str(folder / "ds"), "--recalibrate", "q", "--board", str(board), "--charuco",
            *charuco, "--overwrite"]
    for out, given in ((board, "--board"), (files["q"][2], "--charuco")):
        before = out.read_bytes()
        assert main([*base, "--write-calibration", str(out)]) == 1
        assert f"is this command's input ({given}" in _one_line(capsys)
        assert out.read_bytes() == before


# ------------------------------------------------------------------------------------------------------------
# a repair that is worse than the calibration


def test_recalibration_from_another_cameras_images_is_refused(case, tmp_path, capsys):
    """q recalibrated from p's images: every label's residual rises; refused in one line naming q and the
    residuals before and after, nothing written; --force keeps it."""
    folder, truth, _ = case
    images = folder / "images"
    charuco = [f"p={images}/p-*.png", f"q={images}/p-*.png", f"r={images}/r-*.png"]
    out = tmp_path / "fixed.toml"
    args = ["check-calibration", str(folder / "ds"), "--recalibrate", "q", "--charuco", *charuco,
            "--write-calibration", str(out)]
    assert main(args) == 1
    line = _one_line(capsys)
    match = re.search(r"recalibrating q raised the labels' median residual from ([0-9.]+) px to ([0-9.]+) px "
                      r"\(camera q: [0-9.]+ -> [0-9.]+ px\).*nothing written.*--force", line)
    assert match, line
    assert float(match[2]) > 10 * float(match[1])
    assert not out.exists()
    assert main([*args, "--force"]) in (0, 2)
    assert "warning: recalibrating q raised" in capsys.readouterr().err
    assert out.exists()


def test_recalibration_from_the_cameras_own_images_is_kept(case, tmp_path, capsys):
    folder, truth, _ = case
    charuco = [f"{n}={folder / 'images'}/{n}-*.png" for n in truth.names]
    out = tmp_path / "fixed.toml"
    assert main(["check-calibration", str(folder / "ds"), "--recalibrate", "q", "--charuco", *charuco,
                 "--write-calibration", str(out)]) == 0
    assert "raised" not in capsys.readouterr().err
    K = read_anipose_calibration(out).cameras.numpy()["K"]
    np.testing.assert_allclose(K[1], truth.cameras.numpy()["K"][1], rtol=0.005, atol=1e-9)


# ------------------------------------------------------------------------------------------------------------
# weak spots: the same images for several cameras; options checked before any work


def test_cameras_given_the_same_images(case, tmp_path, capsys):
    folder, _, files = case
    for n in ("a", "b"):
        (tmp_path / n).mkdir()
        for f in files["p"]:
            shutil.copy(f, tmp_path / n / f.name)
    same = f"{folder / 'images'}/p-*.png"
    out = str(tmp_path / "c.toml")
    assert main(["calibrate", f"w={same}", f"x={same}", f"y={same}", f"z={same}", *BOARD, "--out", out]) == 1
    assert "cameras w, x, y, z are given the same source" in _one_line(capsys)
    assert main(["calibrate", f"a={tmp_path / 'a'}", f"b={tmp_path / 'b'}", *_sources(case)[2:], *BOARD,
                 "--out", out]) == 1
    line = _one_line(capsys)
    assert "cameras a, b show identical board views" in line and "--allow-identical-views" in line
    assert not (tmp_path / "c.toml").exists()


def test_labels_are_checked_before_any_work(case, tmp_path, capsys, monkeypatch):
    import s3k.cli.calibrate as calibrate

    def no_work(*args, **kwargs):
        raise AssertionError("calibrated before checking the options")

    monkeypatch.setattr(calibrate, "calibrate_sources", no_work)
    base = ["calibrate", *_sources(case), *BOARD, "--out", str(tmp_path / "c.toml")]
    assert main([*base, "--labels", "z=x.h5"]) == 1
    assert "--labels: camera 'z' is not calibrated here" in _one_line(capsys)
    assert main([*base, "--labels", f"p={tmp_path / 'missing.h5'}"]) == 1
    assert "missing.h5" in _one_line(capsys)
    assert main([*base, "--labels", "../p=x.h5"]) == 1
    assert "camera name '../p'" in _one_line(capsys)
