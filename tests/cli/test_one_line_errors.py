"""Files s3k reads from elsewhere that are broken or hostile end in one line naming the file, never in a
traceback: Latin-1 CSVs, truncated 3D CSVs, XML with entities, calibrations whose rotations are none,
frame ids beyond 64 bits, image patterns that leave the dataset."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers.recordings import CAMS
from helpers.synthetic_rig import make_dataset

from s3k import cli

ROTATION_1E300 = "rotation = [ 1e300, 0.0, 0.0,]"


def one_line(capsys, argv: list[str], *needles: str) -> str:
    capsys.readouterr()
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    return err


def _import_argv(import_recording, calibration: Path, out: Path, *extra: str) -> list[str]:
    root = import_recording["root"]
    return ["import", "--calibration", str(calibration), "--videos",
            *[f"{cam}={root / cam}.mkv" for cam in CAMS], "--out", str(out), *extra]


def test_a_latin1_dlc_csv(import_recording, tmp_path, capsys):
    root = import_recording["root"]
    files = []
    for cam in CAMS:
        text = (root / f"CollectedData_{cam}.csv").read_text().replace("scorer,me", "scorer,Jos\u00e9", 1)
        (tmp_path / f"{cam}.csv").write_bytes(text.encode("latin-1"))
        files.append(f"{cam}={tmp_path / cam}.csv")
    argv = _import_argv(import_recording, root / "calibration.toml", tmp_path / "ds", "--dlc", *files)
    one_line(capsys, argv, "north.csv, line 1", "not UTF-8", "save the file as UTF-8")
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("content, needle", [
    (b"a_x,a_y,a_z,a_error,a_ncams,a_score,fnum\n0,0,0,0,2,1,0\n1,2,3,0.5", "line 3"),  # cut mid-row
    (b"a_x,a_y,a_z,a_error,a_ncams,a_score,fnum\n0,0,0,0,2,1,0\n1,2,\xff,0,2,1,1\n", "not UTF-8"),
])
def test_a_truncated_or_non_utf8_tracks_csv(tmp_path, capsys, content, needle):
    pytest.importorskip("pynwb")
    csv = tmp_path / "points3d.csv"
    csv.write_bytes(content)
    one_line(capsys, ["export-tracks", str(csv), "--format", "nwb", "--out", str(tmp_path / "t.nwb"), "--fps",
                      "30"], str(csv), needle)
    assert not (tmp_path / "t.nwb").exists()


def _rotated(import_recording, tmp_path: Path, rotation: str) -> Path:
    lines = (import_recording["root"] / "calibration.toml").read_text().splitlines()
    i = next(i for i, line in enumerate(lines) if line.startswith("rotation"))
    lines[i] = rotation
    path = tmp_path / "calibration.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_rotation_of_1e300_in_a_toml_calibration(import_recording, tmp_path, capsys):
    calibration = _rotated(import_recording, tmp_path, ROTATION_1E300)
    one_line(capsys, _import_argv(import_recording, calibration, tmp_path / "ds", "--keypoints", "a"),
             str(calibration), "camera north", "rotation")


OPENCV = """%YAML:1.0
---
K: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 70., 0., 31.5, 0., 70., 23.5, 0., 0., 1. ]
R: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ {r} ]
T: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 400. ]
"""

XML_WITH_ENTITIES = """<?xml version="1.0"?>
<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">]>
<opencv_storage>
<K type_id="opencv-matrix"><rows>3</rows><cols>3</cols><dt>d</dt><data>70 0 31.5 0 70 23.5 0 0 1</data></K>
<R type_id="opencv-matrix"><rows>3</rows><cols>3</cols><dt>d</dt><data>&lol2;1 0 0 0 1 0 0 0 1</data></R>
<T type_id="opencv-matrix"><rows>3</rows><cols>1</cols><dt>d</dt><data>0 0 400</data></T>
</opencv_storage>
"""


@pytest.mark.parametrize("kind, needle", [
    ("scaled", "not a rotation"),  # a matrix, but 2 x a rotation
    ("rodrigues", "rotation"),  # a Rodrigues vector of 1e300
    ("entities", "DOCTYPE or entities"),
])
def test_opencv_calibrations_that_are_not(import_recording, tmp_path, capsys, kind, needle):
    folder = tmp_path / "calibration"
    folder.mkdir()
    for cam in CAMS:
        if kind == "entities":
            (folder / f"{cam}.xml").write_text(XML_WITH_ENTITIES)
            continue
        r = "2., 0., 0., 0., 1., 0., 0., 0., 1." if kind == "scaled" else "1e300, 0., 0."
        text = OPENCV.replace("{r}", r).replace("cols: 3\n   dt: d\n   data: [ 1e300",
                                                "cols: 1\n   dt: d\n   data: [ 1e300")
        (folder / f"{cam}.yaml").write_text(text)
    one_line(capsys, _import_argv(import_recording, folder, tmp_path / "ds", "--keypoints", "a"), needle)
    assert not (tmp_path / "ds").exists()


@pytest.fixture
def dataset(tmp_path):
    return make_dataset(tmp_path / "ds", size=32, labelled=2, unlabelled=1, test=0)


def test_validate_a_frame_id_of_27_digits(dataset, capsys):
    frames = dataset / "frames.csv"
    frames.write_text(frames.read_text().replace("\n2,", "\n123456789012345678901234567,"))
    capsys.readouterr()
    assert cli.main(["validate", str(dataset)]) == 1
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert "frames.csv" in captured.out and "123456789012345678901234567" in captured.out


def test_an_images_pattern_that_leaves_the_dataset(dataset, capsys, tmp_path):
    outside = tmp_path / "outside"
    shutil.copytree(dataset / "images", outside)  # the files are there: the pattern alone is refused
    meta = json.loads((dataset / "s3k.json").read_text())
    meta["images"]["pattern"] = "../outside/{camera}/{frame:06d}.png"
    (dataset / "s3k.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert cli.main(["validate", str(dataset)]) == 1
    assert "images.pattern" in capsys.readouterr().out
    one_line(capsys, ["train", str(dataset), "--out", str(tmp_path / "run")], "images.pattern",
             "inside the dataset folder")
    assert not (tmp_path / "run").exists()
