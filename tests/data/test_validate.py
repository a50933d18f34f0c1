"""`s3k validate`: exit codes, every problem reported with its file and field, and the summary."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from s3k.cli import main
from s3k.data import DatasetWriter

KEYPOINTS = ["front", "tongue", "heel"]
CAMERAS = ["left", "right"]
W, H = 20, 14


def make_dataset(root: Path) -> Path:
    """Two cameras, 4 frames (2 labelled, 1 unlabelled, 1 test); every keypoint labelled in both views of
    the labelled frames except 'heel' in 'right'."""
    rng = np.random.default_rng(0)
    K = np.tile([[15.0, 0.0, 9.5], [0.0, 15.0, 6.5], [0.0, 0.0, 1.0]], (2, 1, 1))
    R = np.tile(np.eye(3), (2, 1, 1))
    t = np.array([[0.0, 0.0, 1.0], [-0.1, 0.0, 1.0]])
    rig = (K, np.zeros((2, 5)), R, t)
    with DatasetWriter(root, KEYPOINTS, CAMERAS, (W, H), calibration=rig) as writer:
        for frame, split in enumerate(["labelled", "labelled", "unlabelled", "test"]):
            X = rng.uniform(-0.3, 0.3, size=(3, 3))  # about 1 in front of both cameras
            labels = None
            if split == "labelled":
                cam = X[None] + t[:, None]  # (C, K, 3) camera coordinates (R = I)
                labels = np.einsum("cij,ckj->cki", K, cam / cam[..., 2:])[..., :2]
                labels[1, 2] = np.nan
            images = rng.integers(0, 256, size=(2, H, W, 3), dtype=np.uint8)
            writer.add_frame(frame, split, images, labels=labels, points3d=X)
    return root


def validate(capsys, *args) -> tuple[int, str]:
    code = main(["validate", *(str(a) for a in args)])
    return code, capsys.readouterr().out


def test_good_dataset_exits_zero_with_summary(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    code, out = validate(capsys, root)
    assert code == 0, out
    assert "ERROR" not in out and "OK" in out
    assert "frames per split: labelled 2, unlabelled 1, test 1" in out
    # Labels table: front/tongue labelled in both cameras of 2 frames, heel only in 'left'.
    table = [line.split() for line in out.splitlines() if line.startswith("  ")]
    rows = {cells[0]: cells[1:] for cells in table if cells[0] in KEYPOINTS}
    assert rows == {"front": ["2", "2"], "tongue": ["2", "2"], "heel": ["2", "0"]}
    assert "ground-truth 3D points: 12" in out
    assert "labels (visible, inside the image) per split: labelled 10, unlabelled 0, test 0" in out
    assert "usable for training): 2 of 2" in out


def test_corrupted_image_exits_non_zero_naming_it(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    (root / "images" / "right" / "000002.png").write_bytes(b"\x89PNG broken")
    code, out = validate(capsys, root)
    assert code != 0
    assert "ERROR   images/right/000002.png (frame 2, camera right): field 'image': cannot decode" in out
    assert "UNUSABLE" in out


def test_image_of_wrong_size_exits_non_zero(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    cv2.imwrite(str(root / "images" / "left" / "000001.png"), np.zeros((H, W + 2, 3), np.uint8))
    code, out = validate(capsys, root)
    assert code != 0
    assert "images/left/000001.png (frame 1, camera left): field 'size': image is 22x14" in out


def test_corrupted_calibration_exits_non_zero_naming_it(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    path = root / "calibration.json"
    cal = json.loads(path.read_text())
    cal["cameras"]["right"]["R"][0][0] = 1.5
    path.write_text(json.dumps(cal))
    code, out = validate(capsys, root)
    assert code != 0
    assert "calibration.json (camera right): field 'cameras.right.R': not a rotation" in out


def test_every_problem_is_reported_not_just_the_first(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    (root / "images" / "left" / "000003.png").write_bytes(b"")
    (root / "images" / "right" / "000000.png").unlink()
    cal = json.loads((root / "calibration.json").read_text())
    cal["cameras"]["left"]["K"][0][0] = float("inf")
    (root / "calibration.json").write_text(json.dumps(cal))
    labels = root / "labels.csv"
    labels.write_text(labels.read_text().replace(",tongue,", ",toe,", 1))
    meta = json.loads((root / "s3k.json").read_text())
    meta["version"] = 7
    (root / "s3k.json").write_text(json.dumps(meta))
    code, out = validate(capsys, root)
    assert code != 0
    for text in (
        "s3k.json: field 'version'",
        "images/left/000003.png (frame 3, camera left): field 'image'",
        "images/right/000000.png (frame 0, camera right): field 'image': image file missing",
        "calibration.json (camera left): field 'cameras.left.K': not finite",
        "labels.csv line 3 (frame 0): field 'keypoint': unknown keypoint 'toe'",
    ):
        assert text in out, out
    assert "UNUSABLE: 5 error(s)" in out


def test_label_outside_image_is_a_warning_unless_strict(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    labels = root / "labels.csv"
    lines = labels.read_text().splitlines()
    cells = lines[1].split(",")
    cells[4] = "-3.0"
    lines[1] = ",".join(cells)
    labels.write_text("\n".join(lines) + "\n")
    code, out = validate(capsys, root)
    assert code == 0
    assert "WARNING labels.csv line 2" in out and "field 'v'" in out and "masked" in out
    code, _ = validate(capsys, root, "--strict")
    assert code == 1


def test_labelled_frame_without_two_views_warns(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    labels = root / "labels.csv"
    kept = [line for line in labels.read_text().splitlines() if not line.startswith("1,right,")]
    labels.write_text("\n".join(kept) + "\n")
    code, out = validate(capsys, root)
    assert code == 0
    assert (
        "WARNING frames.csv line 3 (frame 1): field 'split': labelled frame without a usable label: "
        "no keypoint is labelled in 2 or more cameras" in out
    )
    assert "usable for training): 1 of 2" in out


def test_missing_metadata_exits_non_zero(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    (root / "s3k.json").unlink()
    code, out = validate(capsys, root)
    assert code != 0 and "s3k.json: file missing" in out


def test_no_images_skips_decoding_but_not_existence(tmp_path: Path, capsys):
    root = make_dataset(tmp_path / "ds")
    (root / "images" / "left" / "000002.png").write_bytes(b"junk")
    code, _ = validate(capsys, root, "--no-images")
    assert code == 0
    (root / "images" / "left" / "000002.png").unlink()
    code, out = validate(capsys, root, "--no-images")
    assert code != 0 and "images/left/000002.png" in out


@pytest.mark.parametrize("limit", [1, 3])
def test_repeated_problems_are_summarized(tmp_path: Path, capsys, limit: int):
    root = make_dataset(tmp_path / "ds")
    for frame in range(4):
        (root / "images" / "left" / f"{frame:06d}.png").write_bytes(b"junk")
    code, out = validate(capsys, root, "--max-per-field", limit)
    assert code != 0
    assert out.count("field 'image': cannot decode") == limit
    assert f"... and {4 - limit} more" in out


def _set_camera_like(root: Path, camera: str, like: str) -> None:
    path = root / "calibration.json"
    cal = json.loads(path.read_text())
    cal["cameras"][camera] = cal["cameras"][like]
    path.write_text(json.dumps(cal))


def test_usable_label_count_counts_triangulable_keypoints(tmp_path: Path):
    from s3k.data import Dataset, usable_label_count, usable_labels

    root = make_dataset(tmp_path / "ds")
    ds = Dataset.open(root, cache="none")
    # front and tongue in both cameras of both labelled frames; heel only in 'left'.
    np.testing.assert_array_equal(usable_labels(ds), [[True, True, False], [True, True, False]])
    assert usable_label_count(ds) == 4
    assert usable_label_count(Dataset.open(root, image_size=(10, 7), cache="none")) == 4  # any image size
    _set_camera_like(root, "right", "left")  # both views from one centre: the rays meet at the camera
    assert usable_label_count(Dataset.open(root, cache="none")) == 0


@pytest.mark.parametrize("case", ["one camera", "degenerate"])
def test_no_usable_label_is_unusable(tmp_path: Path, capsys, case: str):
    root = make_dataset(tmp_path / "ds")
    if case == "one camera":
        labels = root / "labels.csv"
        kept = [line for line in labels.read_text().splitlines() if ",right," not in line]
        labels.write_text("\n".join(kept) + "\n")
    else:
        _set_camera_like(root, "right", "left")
    code, out = validate(capsys, root)
    assert code == 1
    errors = [line for line in out.splitlines() if line.startswith("ERROR")]
    assert errors == [
        "ERROR   labels.csv: no labelled frame has a usable label (2 labelled frames): training needs a "
        "keypoint labelled in 2 or more cameras whose triangulation lies in front of a camera and inside its "
        "image"
    ]
    assert "usable for training): 0 of 2" in out
    # the two labelled frames without a usable label, and the right camera without heel (or any) labels;
    # a camera with another's parameters is also the calibration check's finding
    copied = case == "degenerate"
    assert ("WARNING calibration: left and right have identical calibration parameters" in out) == copied
    assert out.splitlines()[-1].startswith(f"UNUSABLE: 1 error(s), {3 + copied} warning(s)")


def _offset_dataset(root: Path, offsets: list[int]) -> Path:
    """Four cameras, 60 consecutive labelled frames of points moving smoothly; camera ``c``'s frame ``i``
    shows the first camera's frame ``i + offsets[c]`` (the recordings of ``test_sync``)."""
    from helpers.offset_recording import H as SH
    from helpers.offset_recording import W as SW
    from helpers.offset_recording import recording, rig

    cams = rig()
    uv = recording(cams, offsets, n_frames=60, seed=2)  # (C, T, K, 2)
    arrays = cams.numpy()
    names = [f"cam{c}" for c in range(len(offsets))]
    keypoints = [f"kp{k}" for k in range(uv.shape[2])]
    with DatasetWriter(root, keypoints, names, (SW, SH),
                       calibration=(arrays["K"], arrays["dist"], arrays["R"], arrays["t"])) as writer:
        for f in range(uv.shape[1]):
            writer.add_frame(f, "labelled", np.zeros((len(names), SH, SW, 3), np.uint8), labels=uv[:, f])
    return root


def test_frame_offsets_are_reported_and_warned(tmp_path: Path, capsys):
    code, out = validate(capsys, _offset_dataset(tmp_path / "late", [0, 0, 4, 0]), "--no-images")
    assert "  cam0: 0 (the reference)" in out and "  cam1: +0 (epipolar residual" in out
    assert "  cam2: +4 (epipolar residual" in out
    assert "WARNING camera cam2: its frame i shows cam0's frame i+4" in out
    assert "--frame-offsets cam2=4" in out
    assert code == 1 and "camera(s) cam2 disagree with the others' labels" in out  # the late camera's labels
    code, out = validate(capsys, _offset_dataset(tmp_path / "sync", [0, 0, 0, 0]), "--no-images", "--strict")
    assert code == 0 and "  cam2: +0 (epipolar residual" in out and "--frame-offsets" not in out


def test_sparse_labels_cannot_tell_frame_offsets(tmp_path: Path, capsys):
    code, out = validate(capsys, make_dataset(tmp_path / "ds"))
    assert code == 0 and "frame offsets: the labels cannot tell" in out


def test_frame_offset_check_cuts_long_stretches_without_labels():
    """Labelled frames far apart in a long recording are laid on a short time axis: the stretch between them
    cut to the lag window, the frames within it kept apart as recorded (in any order)."""
    from s3k.data.validate import _time_rows

    times = np.array([10**9 + 1, 0, 2, 1, 10**9])
    np.testing.assert_array_equal(_time_rows(times, 21), [24, 0, 2, 1, 23])


def test_check_calibration_reports_frame_offsets_too(tmp_path: Path, capsys):
    """A camera out of step shows in check-calibration as a camera whose labels disagree: the offset the
    labels' motion gives is printed beside it, with the option to import with."""
    from s3k import cli

    assert cli.main(["check-calibration", str(_offset_dataset(tmp_path / "late", [0, 0, 4, 0]))]) in (0, 2)
    out, err = capsys.readouterr()
    assert "  cam2: +4 (epipolar residual" in out
    assert "warning: camera cam2: its frame i shows cam0's frame i+4" in err
    assert "--frame-offsets cam2=4" in err
    assert cli.main(["check-calibration", str(_offset_dataset(tmp_path / "sync", [0, 0, 0, 0]))]) == 0
    out, err = capsys.readouterr()
    assert "  cam2: +0 (epipolar residual" in out and "--frame-offsets" not in out + err
