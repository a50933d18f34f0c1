"""Dataset folder format: round trips, errors that name file and field, image cache, resized loading."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers.synthetic_rig import count_decodes

from s3k.data import Dataset, DatasetError, DatasetWarning, DatasetWriter, check_dataset
from s3k.data.tables import CALIBRATION_COLUMNS
from s3k.geometry.warp import crop_resize_matrix, resize_crop

KEYPOINTS = ["corner_a", "corner_b", "corner_c"]
CAMERAS = ["cam0", "cam1", "cam2"]
W, H = 24, 16


def rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_rig(rng: np.random.Generator, C: int = len(CAMERAS)):
    K = np.tile(np.array([[20.0, 0.0, (W - 1) / 2], [0.0, 21.0, (H - 1) / 2], [0.0, 0.0, 1.0]]), (C, 1, 1))
    K[:, 0, 0] += rng.uniform(-1, 1, C)
    dist = rng.normal(scale=0.01, size=(C, 5))
    R = np.stack([rotation(rng) for _ in range(C)])
    t = rng.normal(size=(C, 3))
    return K, dist, R, t


def write_dataset(
    root: Path,
    n_frames: int = 6,
    per_frame: bool = False,
    seed: int = 0,
    points: bool = True,
) -> dict:
    """Write a tiny dataset and return what was written, for comparisons."""
    rng = np.random.default_rng(seed)
    C, K = len(CAMERAS), len(KEYPOINTS)
    static = None if per_frame else random_rig(rng)
    written = {"ids": [], "splits": [], "images": [], "cal": [], "uv": [], "points": [], "instance": []}
    splits = ["labelled", "labelled", "unlabelled", "unlabelled", "test", "test"]
    with DatasetWriter(
        root,
        KEYPOINTS,
        CAMERAS,
        (W, H),
        units="m",
        calibration=static,
        skeleton=[["corner_a", "corner_b"]],
        description="tiny test set",
        source={"generator": "tests"},
    ) as writer:
        for i in range(n_frames):
            frame = 10 + 3 * i  # ids need not start at 0 nor be contiguous
            split = splits[i % len(splits)]
            images = rng.integers(0, 256, size=(C, H, W, 3), dtype=np.uint8)
            cal = random_rig(rng) if per_frame else static
            uv = np.stack([rng.uniform(0, W - 1, (C, K)), rng.uniform(0, H - 1, (C, K))], -1)
            uv[rng.random((C, K)) < 0.3] = np.nan  # partial labels
            X = rng.normal(size=(K, 3)) if points else None
            writer.add_frame(
                frame,
                split,
                images,
                calibration=cal if per_frame else None,
                labels=uv,
                points3d=X,
                extra={"instance": i % 2},
            )
            for key, value in zip(written, (frame, split, images, cal, uv, X, str(i % 2))):
                written[key].append(value)
    return written


@pytest.fixture
def tiny(tmp_path: Path):
    root = tmp_path / "tiny"
    return root, write_dataset(root)


# ---------------------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize("per_frame", [False, True])
def test_round_trip_same_arrays(tmp_path: Path, per_frame: bool):
    root = tmp_path / "ds"
    w = write_dataset(root, per_frame=per_frame)
    ds = Dataset.open(root, cache="none")
    assert ds.keypoints == KEYPOINTS and ds.cameras == CAMERAS
    assert ds.image_size == (W, H) and ds.units == "m"
    assert ds.static_calibration is not per_frame
    assert (root / ("calibration.csv" if per_frame else "calibration.json")).is_file()
    assert ds.skeleton == [("corner_a", "corner_b")] and ds.description == "tiny test set"
    assert ds.source == {"generator": "tests"}
    ids = np.array(w["ids"])
    np.testing.assert_array_equal(ds.frames(), ids)
    for split in ("labelled", "unlabelled", "test"):
        np.testing.assert_array_equal(ds.frames(split), ids[np.array(w["splits"]) == split])
    np.testing.assert_array_equal(ds.column("instance"), w["instance"])

    order = ids[::-1]  # any order, repeats allowed
    order = np.concatenate([order, order[:2]])
    pick = [list(ids).index(f) for f in order]
    np.testing.assert_array_equal(ds.images(order), np.stack([w["images"][i] for i in pick]))

    cal = ds.calibration(order, dtype=np.float64).numpy()
    for j, name in enumerate(("K", "dist", "R", "t")):
        expected = np.stack([w["cal"][i][j] for i in pick])
        np.testing.assert_array_equal(cal[name], expected)  # exact: floats are written in full

    uv, mask = ds.labels(order)
    uv_w = np.stack([w["uv"][i] for i in pick])
    np.testing.assert_array_equal(mask, np.isfinite(uv_w).all(-1))
    np.testing.assert_array_equal(uv[mask], uv_w[mask].astype(np.float32))
    assert (uv[~mask] == 0).all()

    X, xmask = ds.points3d(order)
    assert xmask.all()
    np.testing.assert_array_equal(X, np.stack([w["points"][i] for i in pick]).astype(np.float32))


def test_calibration_returns_cameras(tiny):
    root, w = tiny
    geometry = pytest.importorskip("s3k.geometry")
    ds = Dataset.open(root, cache="none")
    cams = ds.calibration(ds.frames()[:2])
    assert isinstance(cams, geometry.Cameras)
    assert tuple(cams.K.shape) == (2, len(CAMERAS), 3, 3) and tuple(cams.t.shape) == (2, len(CAMERAS), 3)
    np.testing.assert_allclose(cams.R[1].numpy(), w["cal"][1][2], atol=1e-6)
    rig = ds.rig()
    assert tuple(rig.K.shape) == (len(CAMERAS), 3, 3)


def test_frames_of_several_splits_follow_the_order_given(tiny):
    root, w = tiny
    ds = Dataset.open(root, cache="none")
    split = np.asarray(w["splits"])
    ids = np.asarray(w["ids"])
    np.testing.assert_array_equal(ds.frames(("test", "labelled")),
                                  np.concatenate([ids[split == "test"], ids[split == "labelled"]]))
    assert sorted(ds.frames(("labelled", "unlabelled", "test")).tolist()) == sorted(ids.tolist())
    assert ds.frames(()).dtype == np.int64 and len(ds.frames(())) == 0
    with pytest.raises(ValueError, match="'train'"):
        ds.frames(("test", "train"))


def test_no_points3d_gives_none(tmp_path: Path):
    write_dataset(tmp_path / "ds", points=False)
    ds = Dataset.open(tmp_path / "ds", cache="none")
    assert ds.points3d(ds.frames()) is None and not ds.has_points3d


def test_occluded_label_is_stored_but_masked(tmp_path: Path):
    rng = np.random.default_rng(1)
    rig = random_rig(rng)
    uv = np.full((len(CAMERAS), len(KEYPOINTS), 2), 5.0)
    visible = np.ones((len(CAMERAS), len(KEYPOINTS)), bool)
    visible[1, 2] = False
    with DatasetWriter(tmp_path / "ds", KEYPOINTS, CAMERAS, (W, H), calibration=rig) as writer:
        writer.add_frame(0, "labelled", np.zeros((3, H, W, 3), np.uint8), labels=uv, visible=visible)
    assert "0,cam1,corner_c,5.0,5.0,0" in (tmp_path / "ds" / "labels.csv").read_text()
    _, mask = Dataset.open(tmp_path / "ds").labels([0])
    np.testing.assert_array_equal(mask[0], visible)


# ---------------------------------------------------------------------------------------------------------
# Image cache and resized loading


def test_disk_cache_matches_and_follows_file_changes(tiny):
    root, w = tiny
    ds = Dataset.open(root, cache="disk")
    ids = ds.frames()
    first = ds.images(ids[[3, 0]])
    caches = sorted((root / ".cache").glob("images-*.u8"))
    assert len(caches) == 1
    np.testing.assert_array_equal(first, np.stack([w["images"][3], w["images"][0]]))
    ds.preload("test")
    np.testing.assert_array_equal(ds.images(ids), np.stack(w["images"]))
    # A second process/run reads the same cache.
    again = Dataset.open(root, cache="disk")
    assert again.fingerprint() == ds.fingerprint()
    again._cache.open()
    assert again._cache.filled.all()  # opening an existing cache keeps what was decoded
    np.testing.assert_array_equal(again.images(ids), np.stack(w["images"]))
    # Rewriting an image changes the fingerprint: the new pixels are seen, not stale cache.
    new = np.full((H, W, 3), 7, np.uint8)
    cv2.imwrite(str(root / "images" / "cam1" / f"{ids[0]:06d}.png"), new)
    changed = Dataset.open(root, cache="disk")
    assert changed.fingerprint() != ds.fingerprint()
    np.testing.assert_array_equal(changed.images(ids[:1])[0, 1], new)


def test_cache_folder_from_environment(tiny, tmp_path: Path, monkeypatch):
    root, w = tiny
    monkeypatch.setenv("S3K_CACHE_DIR", str(tmp_path / "elsewhere"))
    ds = Dataset.open(root, cache="disk")
    np.testing.assert_array_equal(ds.images(ds.frames()), np.stack(w["images"]))
    assert not (root / ".cache").exists()
    assert len(list((tmp_path / "elsewhere").glob("*/images-*.u8"))) == 1


@pytest.mark.parametrize("cache", ["memory", "none"])
def test_memory_and_uncached_images_agree(tiny, cache: str):
    root, w = tiny
    ds = Dataset.open(root, cache=cache, workers=2)
    ids = ds.frames()
    np.testing.assert_array_equal(ds.images(ids), np.stack(w["images"]))
    assert not (root / ".cache").exists()


def test_held_frames_serve_every_view_without_decoding_again(tiny, monkeypatch):
    """``hold_frames``: a resized view keeps the stored images it decodes; the full-size view and another
    size then read them from memory, the same pixels as decoded from the files."""
    import s3k.data.sources as sources

    root, w = tiny
    decoded = count_decodes(monkeypatch, sources)
    full = Dataset.open(root, cache="none")
    full.hold_frames()
    ids = full.frames()
    small = full.with_cache("memory").resized((W // 2, H // 2))
    expected, _ = resize_crop(np.stack(w["images"]), None, None, (W // 2, H // 2))
    np.testing.assert_array_equal(small.images(ids), expected)
    assert len(decoded) == len(ids) * len(CAMERAS)
    np.testing.assert_array_equal(full.images(ids), np.stack(w["images"]))
    other = full.resized((W // 4, H // 4))
    np.testing.assert_array_equal(other.images(ids[:2]), resize_crop(np.stack(w["images"][:2]), None, None,
                                                                      (W // 4, H // 4))[0])
    assert len(decoded) == len(ids) * len(CAMERAS)  # nothing decoded again
    full.release_frames()
    full.images(ids[:1])
    assert len(decoded) == (len(ids) + 1) * len(CAMERAS)
    assert full.stored_mib == pytest.approx(len(ids) * len(CAMERAS) * W * H * 3 / 2**20)


def test_open_resized_updates_images_K_and_labels(tiny):
    root, w = tiny
    size = (W // 2, H // 2)
    full = Dataset.open(root, cache="none")
    ds = Dataset.open(root, image_size=size, cache="memory")
    ids = ds.frames()
    assert ds.image_size == size and ds.source_image_size == (W, H)
    expected, _ = resize_crop(full.images(ids), None, None, size)
    np.testing.assert_array_equal(ds.images(ids), expected)
    M = crop_resize_matrix((0, 0, W, H), size)
    K, K_full = ds.calibration(ids, np.float64).K.numpy(), full.calibration(ids, np.float64).K.numpy()
    np.testing.assert_allclose(K, M @ K_full, atol=1e-12)
    uv_full, mask_full = full.labels(ids)
    uv, mask = ds.labels(ids)
    np.testing.assert_array_equal(mask, mask_full)
    np.testing.assert_allclose(uv[mask], 0.5 * (uv_full[mask] + 0.5) - 0.5, atol=1e-5)


def test_open_cropped_masks_labels_outside_the_crop(tiny):
    root, _ = tiny
    full = Dataset.open(root, cache="none")
    box = (4, 2, 16, 14)
    ds = Dataset.open(root, crop_box=box, cache="none")
    ids = ds.frames()
    assert ds.image_size == (12, 12)
    np.testing.assert_array_equal(ds.images(ids), full.images(ids)[:, :, 2:14, 4:16])
    uv_full, mask_full = full.labels(ids)
    inside = (uv_full[..., 0] >= 3.5) & (uv_full[..., 0] <= 15.5) & (uv_full[..., 1] >= 1.5)
    inside &= uv_full[..., 1] <= 13.5
    uv, mask = ds.labels(ids)
    np.testing.assert_array_equal(mask, mask_full & inside)
    np.testing.assert_allclose(uv[mask], uv_full[mask] - [4, 2], atol=1e-5)


# ---------------------------------------------------------------------------------------------------------
# Validation on load: every error names the file and the field.


def _edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _edit_text(path: Path, old: str, new: str, count: int = 1) -> None:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path}"
    path.write_text(text.replace(old, new, count))


def _first_data_line(path: Path) -> str:
    return path.read_text().splitlines()[1]


def _set_json(file, keys, value):
    def change(data):
        target = data
        for k in keys[:-1]:
            target = target[k]
        target[keys[-1]] = value

    return lambda root: _edit_json(root / file, change)


def _break_label(column: int, value: str):
    def corrupt(root: Path):
        path = root / "labels.csv"
        line = _first_data_line(path)
        cells = line.split(",")
        cells[column] = value
        _edit_text(path, line, ",".join(cells))

    return corrupt


def _scale_R(root: Path):
    _edit_json(
        root / "calibration.json",
        lambda d: d["cameras"]["cam1"].__setitem__(
            "R", (1.1 * np.asarray(d["cameras"]["cam1"]["R"])).tolist()
        ),
    )


def _reflect_R(root: Path):
    _edit_json(
        root / "calibration.json",
        lambda d: d["cameras"]["cam2"].__setitem__("R", (-np.asarray(d["cameras"]["cam2"]["R"])).tolist()),
    )


CORRUPTIONS = {
    # name: (corrupt(root), file named, field named, extra text in the message)
    "missing metadata": (lambda r: (r / "s3k.json").unlink(), "s3k.json", None, "missing"),
    "bad version": (_set_json("s3k.json", ["version"], 99), "s3k.json", "version", "99"),
    "bad format name": (_set_json("s3k.json", ["format"], "coco"), "s3k.json", "format", "coco"),
    "bad image size": (_set_json("s3k.json", ["image_size"], [24]), "s3k.json", "image_size", "[W, H]"),
    "duplicate camera": (
        _set_json("s3k.json", ["cameras"], ["cam0", "cam0", "cam2"]),
        "s3k.json",
        "cameras",
        "duplicate",
    ),
    "image pattern without camera": (
        _set_json("s3k.json", ["images"], {"type": "png", "pattern": "images/{frame:06d}.png"}),
        "s3k.json",
        "images.pattern",
        "{camera}",
    ),
    "unknown image type": (_set_json("s3k.json", ["images"], {"type": "hdf5"}), "s3k.json", "images", "hdf5"),
    "keypoint name with a comma": (
        _set_json("s3k.json", ["keypoints"], ["corner_a", "corner,b", "corner_c"]),
        "s3k.json",
        "keypoints",
        "commas",
    ),
    "bad split": (
        lambda r: _edit_text(r / "frames.csv", "unlabelled", "unlabeled"),
        "frames.csv",
        "split",
        "unlabeled",
    ),
    "bad frame id": (lambda r: _edit_text(r / "frames.csv", "\n10,", "\nten,"), "frames.csv", "frame", "ten"),
    "duplicate frame": (
        lambda r: _edit_text(r / "frames.csv", "\n13,", "\n10,"),
        "frames.csv",
        "frame",
        "repeated",
    ),
    "missing image": (
        lambda r: (r / "images" / "cam1" / "000013.png").unlink(),
        "images/cam1/000013.png",
        "image",
        "missing",
    ),
    "calibration not finite": (
        _set_json("calibration.json", ["cameras", "cam1", "t"], [0.0, float("nan"), 1.0]),
        "calibration.json",
        "cameras.cam1.t",
        "not finite",
    ),
    "R not orthonormal": (_scale_R, "calibration.json", "cameras.cam1.R", "not a rotation"),
    "R reflection": (_reflect_R, "calibration.json", "cameras.cam2.R", "det R = -1"),
    "K wrong shape": (
        _set_json("calibration.json", ["cameras", "cam0", "K"], [[1.0, 0.0], [0.0, 1.0]]),
        "calibration.json",
        "cameras.cam0.K",
        "shape",
    ),
    "calibration unknown camera": (
        lambda r: _edit_json(
            r / "calibration.json", lambda d: d["cameras"].__setitem__("cam9", d["cameras"]["cam0"])
        ),
        "calibration.json",
        "cameras.cam9",
        "unknown camera",
    ),
    "calibration missing camera": (
        lambda r: _edit_json(r / "calibration.json", lambda d: d["cameras"].pop("cam2")),
        "calibration.json",
        "cameras.cam2",
        "missing",
    ),
    "label unknown camera": (_break_label(1, "cam7"), "labels.csv line 2", "camera", "cam7"),
    "label unknown keypoint": (_break_label(2, "nose"), "labels.csv line 2", "keypoint", "nose"),
    "label unknown frame": (_break_label(0, "999"), "labels.csv line 2", "frame", "999"),
    "label not a number": (_break_label(3, "abc"), "labels.csv line 2", "u", "abc"),
    "label bad visible": (_break_label(5, "maybe"), "labels.csv line 2", "visible", "maybe"),
    "points3d unknown keypoint": (
        lambda r: _edit_text(r / "points3d.csv", ",corner_b,", ",corner_z,"),
        "points3d.csv",
        "keypoint",
        "corner_z",
    ),
    "points3d wrong column count": (
        lambda r: _edit_text(r / "points3d.csv", "\n10,corner_a,", "\n10,corner_a,inf,0,"),
        "points3d.csv",
        None,
        "values but the header",
    ),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_corruption_is_reported_naming_file_and_field(tiny, name: str):
    root, _ = tiny
    corrupt, file, fld, text = CORRUPTIONS[name]
    corrupt(root)
    with pytest.raises(DatasetError) as info:
        Dataset.open(root)
    message = str(info.value)
    assert file in message, message
    if fld is not None:
        assert f"field '{fld}'" in message, message
    assert text in message, message
    assert info.value.problems and all(p.severity == "error" for p in info.value.problems)
    # check_dataset finds the same problem without raising.
    problems, _ = check_dataset(root, check_images=False)
    assert any(file in str(p) and (fld is None or p.field == fld) for p in problems)


def test_points3d_non_finite_value(tiny):
    root, _ = tiny
    path = root / "points3d.csv"
    line = _first_data_line(path)
    cells = line.split(",")
    cells[3] = "nan"
    _edit_text(path, line, ",".join(cells))
    with pytest.raises(DatasetError, match=r"points3d.csv line 2 \(frame 10, keypoint corner_a\): field 'y'"):
        Dataset.open(root)


def _per_frame(tmp_path: Path) -> Path:
    root = tmp_path / "pf"
    write_dataset(root, per_frame=True)
    return root


def test_per_frame_calibration_bad_rotation_names_line_frame_camera(tmp_path: Path):
    root = _per_frame(tmp_path)
    path = root / "calibration.csv"
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")  # line 6 of the file
    r00 = CALIBRATION_COLUMNS.index("R00")
    cells[r00] = str(float(cells[r00]) + 0.2)
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as info:
        Dataset.open(root)
    msg = str(info.value)
    assert (
        f"calibration.csv line 6 (frame {cells[0]}, camera {cells[1]}): field 'R00..R22': not a rotation"
        in msg
    )


def test_per_frame_calibration_not_finite_and_missing_row(tmp_path: Path):
    root = _per_frame(tmp_path)
    path = root / "calibration.csv"
    lines = path.read_text().splitlines()
    cells = lines[1].split(",")
    cells[CALIBRATION_COLUMNS.index("ty")] = "nan"
    lines[1] = ",".join(cells)
    dropped = lines.pop(3).split(",")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as info:
        Dataset.open(root)
    msg = "\n".join(str(p) for p in info.value.problems)
    assert "calibration.csv line 2 (frame 10, camera cam0): field 'tx..tz': not finite" in msg
    assert f"(frame {dropped[0]}, camera {dropped[1]}): no calibration row" in msg


def test_byte_order_mark_is_accepted(tiny):
    root, _ = tiny
    for name in ("s3k.json", "frames.csv", "labels.csv"):
        path = root / name
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())  # as spreadsheet programs save UTF-8
    assert len(Dataset.open(root, cache="none").frames("labelled")) == 2


def test_every_error_is_collected(tiny):
    root, _ = tiny
    CORRUPTIONS["bad split"][0](root)
    CORRUPTIONS["R not orthonormal"][0](root)
    CORRUPTIONS["label unknown keypoint"][0](root)
    CORRUPTIONS["missing image"][0](root)
    with pytest.raises(DatasetError) as info:
        Dataset.open(root)
    fields = {(p.file, p.field) for p in info.value.problems}
    assert {
        ("frames.csv", "split"),
        ("calibration.json", "cameras.cam1.R"),
        ("labels.csv", "keypoint"),
        ("images/cam1/000013.png", "image"),
    } <= fields


def test_label_outside_image_warns_and_is_masked(tiny):
    root, w = tiny
    path = root / "labels.csv"
    line = _first_data_line(path)
    frame, cam, kp = line.split(",")[:3]
    cells = line.split(",")
    cells[3] = str(W + 3.25)
    _edit_text(path, line, ",".join(cells))
    with pytest.warns(DatasetWarning) as record:
        ds = Dataset.open(root, cache="none")
    message = str(record[0].message)
    assert "labels.csv line 2" in message and "field 'u'" in message and "outside" in message
    _, mask = ds.labels([int(frame)])
    c, k = CAMERAS.index(cam), KEYPOINTS.index(kp)
    assert not mask[0, c, k]
    expected = np.isfinite(w["uv"][w["ids"].index(int(frame))]).all(-1)
    expected[c, k] = False
    np.testing.assert_array_equal(mask[0], expected)


def test_label_on_image_edge_is_inside(tiny):
    root, _ = tiny
    path = root / "labels.csv"
    line = _first_data_line(path)
    cells = line.split(",")
    cells[3], cells[4] = str(W - 0.5), "-0.5"  # the outer edge of the border pixels is still in the image
    _edit_text(path, line, ",".join(cells))
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)
        ds = Dataset.open(root, cache="none")
    _, mask = ds.labels([int(cells[0])])
    assert mask[0, CAMERAS.index(cells[1]), KEYPOINTS.index(cells[2])]


def test_unreadable_image_raises_naming_the_file_when_decoded(tiny):
    root, _ = tiny
    (root / "images" / "cam2" / "000016.png").write_bytes(b"not a png")
    ds = Dataset.open(root, cache="memory")  # tables are fine; pixels are read on first use
    ds.images([10])
    with pytest.raises(DatasetError, match=r"images/cam2/000016.png"):
        ds.images([16])


def test_wrong_image_size_raises_naming_file_and_field(tiny):
    root, _ = tiny
    cv2.imwrite(str(root / "images" / "cam0" / "000013.png"), np.zeros((H + 1, W, 3), np.uint8))
    ds = Dataset.open(root, cache="none")
    with pytest.raises(DatasetError, match=r"images/cam0/000013.png \(frame 13, camera cam0\): field 'size'"):
        ds.images([13])


# ---------------------------------------------------------------------------------------------------------
# Writer input checks


def test_writer_rejects_bad_input(tmp_path: Path):
    rng = np.random.default_rng(0)
    rig = random_rig(rng)
    images = np.zeros((len(CAMERAS), H, W, 3), np.uint8)
    w = DatasetWriter(tmp_path / "ds", KEYPOINTS, CAMERAS, (W, H), calibration=rig)
    with pytest.raises(ValueError, match="split"):
        w.add_frame(0, "train", images)
    with pytest.raises(ValueError, match=r"images\[0\]"):
        w.add_frame(0, "labelled", images[:, :-1])
    with pytest.raises(ValueError, match="labels"):
        w.add_frame(0, "labelled", images, labels=np.zeros((2, 3, 2)))
    w.add_frame(0, "labelled", images)
    with pytest.raises(ValueError, match="added twice"):
        w.add_frame(0, "labelled", images)
    bad = list(random_rig(rng))
    bad[2] = bad[2] * 2
    with pytest.raises(ValueError, match=r"calibration.R .*not a rotation"):
        DatasetWriter(tmp_path / "other", KEYPOINTS, CAMERAS, (W, H), calibration=bad)
    with pytest.raises(ValueError, match="cameras"):
        DatasetWriter(tmp_path / "x", KEYPOINTS, ["a/b"], (W, H))
    with pytest.raises(FileExistsError):
        DatasetWriter(tmp_path / "ds", KEYPOINTS, CAMERAS, (W, H), calibration=rig)


def test_writer_detects_static_calibration(tmp_path: Path):
    rig = random_rig(np.random.default_rng(0))
    with DatasetWriter(tmp_path / "ds", KEYPOINTS, CAMERAS, (W, H)) as w:
        for f in range(3):
            w.add_frame(f, "unlabelled", np.zeros((3, H, W, 3), np.uint8), calibration=rig)
    ds = Dataset.open(tmp_path / "ds")
    assert ds.static_calibration and not (tmp_path / "ds" / "calibration.csv").exists()


# ---------------------------------------------------------------------------------------------------------
# Video datasets


def test_video_dataset_reads_frames_by_video_index(tmp_path: Path):
    rng = np.random.default_rng(0)
    C = 2
    n = 4
    frames = rng.integers(0, 256, size=(n, C, H, W, 3), dtype=np.uint8)
    videos = {}
    for c in range(C):
        path = tmp_path / f"v{c}.avi"
        out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10, (W, H))  # lossless
        if not out.isOpened():
            pytest.skip("OpenCV has no FFV1 encoder")
        for i in range(n):
            out.write(cv2.cvtColor(frames[i, c], cv2.COLOR_RGB2BGR))
        out.release()
        videos[CAMERAS[c]] = path
    rig = [a[:C] for a in random_rig(rng)]
    with DatasetWriter(tmp_path / "ds", KEYPOINTS, CAMERAS[:C], (W, H), calibration=rig, videos=videos) as w:
        for f, vf in ((100, 2), (101, 0), (102, 3)):
            w.add_frame(f, "unlabelled", extra={"video_frame": vf})
    meta = json.loads((tmp_path / "ds" / "s3k.json").read_text())
    assert meta["images"] == {
        "type": "video",
        "videos": {"cam0": "videos/cam0.avi", "cam1": "videos/cam1.avi"},
    }
    ds = Dataset.open(tmp_path / "ds", cache="memory")
    np.testing.assert_array_equal(ds.images([101, 102, 100]), frames[[0, 3, 2]])
    problems, _ = check_dataset(tmp_path / "ds")
    # The videos decode; without labelled frames the dataset is valid but has nothing to train on yet.
    assert [(p.file, p.severity) for p in problems] == [("frames.csv", "warning")]
    assert "no labelled frames: the dataset can be inspected and labelled" in problems[0].message


def test_dataset_error_is_one_line_user_error_with_every_problem(tiny):
    from s3k.base.errors import UserError

    root, _ = tiny
    CORRUPTIONS["bad split"][0](root)
    CORRUPTIONS["label unknown keypoint"][0](root)
    CORRUPTIONS["missing image"][0](root)
    with pytest.raises(DatasetError) as info:
        Dataset.open(root)
    error = info.value
    assert isinstance(error, UserError)
    assert "\n" not in str(error)
    assert str(error) == f"dataset {root}: {error.problems[0]} (and {len(error.problems) - 1} more errors)"
    assert str(error).startswith(f"dataset {root}: frames.csv line ")
    assert len(error.problems) >= 3


def test_truncated_png_raises_one_line_naming_the_file(tiny, capfd):
    root, _ = tiny
    path = root / "images" / "cam1" / "000013.png"
    path.write_bytes(path.read_bytes()[:60])  # cut inside the pixel data
    for cache in ("none", "memory"):
        ds = Dataset.open(root, cache=cache)
        with pytest.raises(DatasetError) as info:
            ds.images([10, 13])
        assert str(info.value) == (
            f"dataset {root}: images/cam1/000013.png (frame 13, camera cam1): field 'image': cannot decode "
            "as an image (truncated or not an image file)"
        )
    assert capfd.readouterr().err == ""  # the decoder's own warnings are not printed besides the message
