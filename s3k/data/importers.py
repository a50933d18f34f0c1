"""Importers: what camera rigs already produce -> an s3k dataset (the ``s3k import`` command).

Parsers, each a plain function returning numpy arrays:
- :func:`read_anipose_calibration` / :func:`write_anipose_calibration`: anipose ``calibration.toml``.
- :func:`read_dlc_csv`: DeepLabCut / Lightning Pose label CSVs (three header rows scorer/bodyparts/coords; one
  CSV per view in Lightning Pose's multi-view layout, see :func:`find_lightning_pose_csvs`).
- :func:`read_sleap_analysis`: SLEAP analysis HDF5 (``sleap-convert --format analysis``).
Videos are read with :mod:`s3k.data.video`.

2D labels come back as a :class:`LabelTable`: ``uv (F, K, 2)`` pixels with NaN where a keypoint is unlabelled,
indexed by video frame id. Pixel (0, 0) is the centre of the top-left pixel in all three tools, as in s3k.
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


# ------------------------------------------------------------------------------------------------------------
# anipose calibration.toml


@dataclass
class RigCalibration:
    """A static rig in the OpenCV model: ``x_cam = R @ x_world + t``.

    Attributes:
        names: camera names, ``C`` of them.
        K: ``(C, 3, 3)`` intrinsics.
        dist: ``(C, 5)`` distortion ``(k1, k2, p1, p2, k3)``.
        R: ``(C, 3, 3)`` world->camera rotations.
        t: ``(C, 3)`` world->camera translations, in ``units``.
        size: ``(C, 2)`` image size ``(W, H)`` in pixels.
        units: length unit of the world frame (``"mm"``, ``"m"``, ``"board squares"``...).
        metadata: the file's ``[metadata]`` table (board description for anipose), kept for writing back.
    """

    names: list[str]
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: np.ndarray
    units: str = "unknown"
    metadata: dict = field(default_factory=dict)

    def select(self, names: list[str]) -> RigCalibration:
        """The cameras ``names``, in that order (``KeyError`` naming the missing camera and those known)."""
        idx = []
        for name in names:
            if name not in self.names:
                raise KeyError(f"camera {name!r} is not in the calibration (it has {', '.join(self.names)})")
            idx.append(self.names.index(name))
        return RigCalibration(
            list(names), self.K[idx], self.dist[idx], self.R[idx], self.t[idx], self.size[idx], self.units,
            dict(self.metadata),
        )

    def centres(self) -> np.ndarray:
        """``(C, 3)`` camera centres ``-R^T t`` in world coordinates."""
        return -np.einsum("cji,cj->ci", self.R, self.t)


def rodrigues_to_matrix_np(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues vector ``(3,)`` -> rotation matrix ``(3, 3)`` (numpy, float64; OpenCV's convention)."""
    rvec = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-12:
        return np.eye(3)
    k = rvec / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * (kx @ kx)


def matrix_to_rodrigues_np(R: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` -> Rodrigues vector ``(3,)`` (numpy, float64), valid up to ``pi``."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rvec.reshape(3)


def _units_from_board(square_length: float | None) -> str:
    # anipose puts the world frame in the unit the user gave the board square in; its documentation and
    # every rig seen so far use millimetres (squares of 10-50). A sub-unit square length means metres.
    if square_length is None:
        return "unknown"
    return "m" if square_length < 1.0 else "mm"


def _field(path: Path, section: str, table: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    if key not in table:
        raise ValueError(f"{path}: section [{section}] has no field {key!r}")
    try:
        value = np.asarray(table[key], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: [{section}] {key} is not numeric: {table[key]!r}") from exc
    if value.shape != shape:
        raise ValueError(f"{path}: [{section}] {key} has shape {value.shape}, expected {shape}")
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{path}: [{section}] {key} has non-finite values: {table[key]!r}")
    return value


def read_anipose_calibration(path: str | Path, units: str | None = None) -> RigCalibration:
    """Read an anipose ``calibration.toml``.

    Each camera section (``[cam_0]``, ``[cam_1]``...) has ``name``, ``size = [W, H]``, ``matrix`` (3x3),
    ``distortions`` (5; fewer are zero-padded), ``rotation`` (Rodrigues, world->camera) and ``translation``.
    A ``[metadata]`` table, when present, describes the board.

    Args:
        path: the TOML file.
        units: world length unit; by default ``[metadata] units`` if present (s3k writes it), else inferred
            from the board's ``square_length`` in ``[metadata]`` or in a ``board.toml`` beside the file
            (anipose's world unit is the unit of the board's square length: ``"mm"`` for lengths >= 1, ``"m"``
            below), else ``"unknown"``.

    Returns:
        The rig, cameras in file order.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from exc
    metadata = data.get("metadata", {})
    if not isinstance(metadata, dict):
        raise ValueError(f"{path}: [metadata] must be a table")
    sections = [k for k, v in data.items() if k != "metadata" and isinstance(v, dict)]
    if not sections:
        raise ValueError(f"{path}: no camera sections (expected [cam_0], [cam_1], ...)")
    names, Ks, dists, Rs, ts, sizes = [], [], [], [], [], []
    for section in sections:
        table = data[section]
        name = table.get("name", section)
        if not isinstance(name, str) or not name:
            raise ValueError(f"{path}: [{section}] name must be a non-empty string, got {name!r}")
        if name in names:
            raise ValueError(f"{path}: [{section}] camera name {name!r} appears twice")
        if table.get("fisheye", False):
            raise ValueError(f"{path}: [{section}] is a fisheye camera; s3k supports the pinhole model only")
        size = _field(path, section, table, "size", (2,))
        if np.any(size <= 0) or np.any(size != np.round(size)):
            raise ValueError(f"{path}: [{section}] size must be two positive integers [W, H], got {size}")
        K = _field(path, section, table, "matrix", (3, 3))
        if abs(K[2, 2]) < 1e-12 or abs(np.linalg.det(K)) < 1e-12:
            raise ValueError(f"{path}: [{section}] matrix is singular: {K.tolist()}")
        raw = table.get("distortions")
        if raw is None:
            raise ValueError(f"{path}: section [{section}] has no field 'distortions'")
        d = np.asarray(raw, dtype=np.float64).reshape(-1)
        if d.size > 5 and np.any(d[5:] != 0):
            raise ValueError(
                f"{path}: [{section}] distortions has {d.size} coefficients; "
                "s3k supports (k1, k2, p1, p2, k3)"
            )
        d = np.concatenate([d[:5], np.zeros(max(0, 5 - d.size))])
        rvec = _field(path, section, table, "rotation", (3,))
        tvec = _field(path, section, table, "translation", (3,))
        names.append(name)
        Ks.append(K / K[2, 2])
        dists.append(d)
        Rs.append(rodrigues_to_matrix_np(rvec))
        ts.append(tvec)
        sizes.append(size.astype(np.int64))
    if units is None and isinstance(metadata.get("units"), str):
        units = metadata["units"]
    if units is None:
        square = metadata.get("square_length")
        board = path.parent / "board.toml"
        if square is None and board.is_file():
            try:
                square = tomllib.loads(board.read_text()).get("square_length")
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"{board}: not valid TOML ({exc})") from exc
        units = _units_from_board(float(square) if square is not None else None)
    return RigCalibration(
        names, np.stack(Ks), np.stack(dists), np.stack(Rs), np.stack(ts), np.stack(sizes), units,
        dict(metadata),
    )


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} to TOML")


def write_anipose_calibration(path: str | Path, calib: RigCalibration) -> None:
    """Write ``calib`` as an anipose ``calibration.toml`` (read back by :func:`read_anipose_calibration`)."""
    lines = []
    for c, name in enumerate(calib.names):
        lines += [
            f"[cam_{c}]",
            f"name = {_toml_value(name)}",
            f"size = {_toml_value([int(v) for v in calib.size[c]])}",
            f"matrix = {_toml_value([[float(v) for v in row] for row in calib.K[c]])}",
            f"distortions = {_toml_value([float(v) for v in calib.dist[c]])}",
            f"rotation = {_toml_value([float(v) for v in matrix_to_rodrigues_np(calib.R[c])])}",
            f"translation = {_toml_value([float(v) for v in calib.t[c]])}",
            "",
        ]
    # anipose ignores unknown metadata keys; s3k records the world unit there so it survives a round trip.
    metadata = dict(calib.metadata)
    if calib.units != "unknown":
        metadata["units"] = calib.units
    lines.append("[metadata]")
    lines += [f"{k} = {_toml_value(v)}" for k, v in metadata.items()]
    lines.append("")
    Path(path).write_text("\n".join(lines))


# ------------------------------------------------------------------------------------------------------------
# 2D labels


@dataclass
class LabelTable:
    """2D keypoints of one camera.

    Attributes:
        keypoints: ``K`` names.
        frame_ids: ``(F,)`` int64 video frame indices, increasing.
        uv: ``(F, K, 2)`` float64 pixels; NaN where unlabelled.
        source: the file it came from (for messages).
    """

    keypoints: list[str]
    frame_ids: np.ndarray
    uv: np.ndarray
    source: str = ""

    def dense(self, num_frames: int, keypoints: list[str] | None = None) -> np.ndarray:
        """``(num_frames, K', 2)`` indexed by frame id (NaN where absent), keypoints in the given order."""
        keypoints = self.keypoints if keypoints is None else keypoints
        order = []
        for name in keypoints:
            if name not in self.keypoints:
                raise KeyError(f"{self.source}: no keypoint {name!r} (it has {', '.join(self.keypoints)})")
            order.append(self.keypoints.index(name))
        out = np.full((num_frames, len(keypoints), 2), np.nan)
        keep = self.frame_ids < num_frames
        out[self.frame_ids[keep]] = self.uv[keep][:, order]
        return out


_DIGITS = re.compile(r"(\d+)")


def frame_id_from_path(image_path: str) -> int | None:
    """The frame index in an image path: the last run of digits in the file's stem (``img0042.png`` -> 42)."""
    stem = Path(image_path.replace("\\", "/")).stem
    runs = _DIGITS.findall(stem)
    return int(runs[-1]) if runs else None


def read_dlc_csv(path: str | Path, frame_ids_from: str = "path") -> LabelTable:
    """Read a DeepLabCut / Lightning Pose label CSV.

    Layout: header rows ``scorer``, (``individuals``, single animal only), ``bodyparts``, ``coords``; then one
    row per image: leading index column(s) with the image path (or a frame number), then ``x, y`` (and
    optionally ``likelihood``, ignored) per bodypart. Empty cells (or NaN) mean unlabelled.

    Args:
        path: the CSV file.
        frame_ids_from: ``"path"`` takes the frame index from the image file name's last digits
            (``img0042.png`` -> 42), falling back to the row when a name has no digits; ``"row"`` numbers
            rows from 0.

    Returns:
        The labels, frames sorted by frame id.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: label CSV not found")
    if frame_ids_from not in ("path", "row"):
        raise ValueError(f"frame_ids_from must be 'path' or 'row', got {frame_ids_from!r}")
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    header: dict[str, list[str]] = {}
    r = 0
    while r < len(rows) and rows[r] and rows[r][0].strip().lower() in ("scorer", "individuals", "bodyparts",
                                                                       "coords"):
        header[rows[r][0].strip().lower()] = rows[r]
        r += 1
    for name in ("scorer", "bodyparts", "coords"):
        if name not in header:
            raise ValueError(
                f"{path}: missing the {name!r} header row (expected three header rows "
                "scorer/bodyparts/coords, each starting with its name)"
            )
    coords_row, parts_row = header["coords"], header["bodyparts"]
    # Leading index columns: those whose coords cell is empty or the row label itself.
    n_index = 1
    while n_index < len(coords_row) and coords_row[n_index].strip() == "":
        n_index += 1
    if "individuals" in header:
        individuals = {v.strip() for v in header["individuals"][n_index:] if v.strip()}
        if len(individuals) > 1:
            raise ValueError(
                f"{path}: multi-animal CSV with individuals {sorted(individuals)}; s3k imports one animal "
                "per recording (split the CSV per individual)"
            )
    keypoints: list[str] = []
    x_col: dict[str, int] = {}
    y_col: dict[str, int] = {}
    for col in range(n_index, len(coords_row)):
        coord = coords_row[col].strip().lower()
        part = parts_row[col].strip() if col < len(parts_row) else ""
        if not part:
            raise ValueError(f"{path}: header row 'bodyparts' is empty at column {col + 1}")
        if coord not in ("x", "y", "likelihood"):
            raise ValueError(
                f"{path}: header row 'coords' column {col + 1} is {coords_row[col]!r}; "
                "expected x, y or likelihood"
            )
        if part not in keypoints:
            keypoints.append(part)
        target = x_col if coord == "x" else y_col if coord == "y" else None
        if target is not None:
            if part in target:
                raise ValueError(f"{path}: bodypart {part!r} has two {coord!r} columns")
            target[part] = col
    for part in keypoints:
        if part not in x_col or part not in y_col:
            raise ValueError(f"{path}: bodypart {part!r} needs both an x and a y column")
    if not keypoints:
        raise ValueError(f"{path}: no bodypart columns")

    ids: list[int] = []
    uvs: list[np.ndarray] = []
    n_cols = len(coords_row)
    for row_no, row in enumerate(rows[r:]):
        line = r + row_no + 1  # 1-based line number for messages
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) > n_cols:
            raise ValueError(f"{path}: line {line} has {len(row)} cells, the header has {n_cols}")
        row = row + [""] * (n_cols - len(row))
        index_text = "/".join(cell.strip() for cell in row[:n_index] if cell.strip())
        frame = None
        if frame_ids_from == "path":
            frame = frame_id_from_path(index_text) if not index_text.isdigit() else int(index_text)
        if frame is None:
            frame = row_no
        uv = np.full((len(keypoints), 2), np.nan)
        for k, part in enumerate(keypoints):
            for a, col in enumerate((x_col[part], y_col[part])):
                cell = row[col].strip()
                if cell == "" or cell.lower() == "nan":
                    continue
                try:
                    uv[k, a] = float(cell)
                except ValueError:
                    raise ValueError(
                        f"{path}: line {line} ({index_text or 'no image path'}), bodypart {part!r} "
                        f"{'xy'[a]}: {cell!r} is not a number"
                    ) from None
        # A keypoint is labelled only when both coordinates are.
        uv[np.isnan(uv).any(axis=1)] = np.nan
        ids.append(frame)
        uvs.append(uv)
    if not ids:
        raise ValueError(f"{path}: no label rows after the header")
    frame_ids = np.asarray(ids, dtype=np.int64)
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
        raise ValueError(
            f"{path}: frame ids {dup} appear on several rows (frame ids come from the image names; use "
            "frame_ids_from='row' if the names do not number the frames)"
        )
    order = np.argsort(frame_ids)
    return LabelTable(keypoints, frame_ids[order], np.stack(uvs)[order], str(path))


def find_lightning_pose_csvs(folder: str | Path, views: list[str]) -> dict[str, Path]:
    """Lightning Pose multi-view layout: one ``CollectedData_<view>.csv`` per view in ``folder``."""
    folder = Path(folder)
    found = {}
    for view in views:
        candidates = [folder / f"CollectedData_{view}.csv", folder / f"CollectedData_{view}_new.csv"]
        hit = next((c for c in candidates if c.is_file()), None)
        if hit is None:
            raise FileNotFoundError(f"{folder}: no CollectedData_{view}.csv for view {view!r}")
        found[view] = hit
    return found


def _decode(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).reshape(-1)]


def read_sleap_analysis(path: str | Path, track: str | int | None = None) -> LabelTable:
    """Read a SLEAP analysis HDF5 file (``sleap-convert --format analysis``).

    SLEAP writes MATLAB-ordered arrays: ``tracks (n_tracks, 2, n_nodes, n_frames)``, ``track_occupancy
    (n_frames, n_tracks)``, ``node_names (n_nodes,)``, ``track_names (n_tracks,)``. Files written without the
    transposition (``tracks (n_frames, n_nodes, 2, n_tracks)``) are recognized too. Missing points are NaN;
    frames where the track is not occupied are NaN.

    Args:
        path: the ``.h5`` file.
        track: track name or index; may be omitted when the file holds one track.

    Returns:
        The labels of every video frame (``frame_ids = 0..n_frames-1``).
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: SLEAP analysis file not found")
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path}: not an HDF5 file ({exc})") from exc
    with h5:
        for key in ("tracks", "node_names"):
            if key not in h5:
                raise ValueError(f"{path}: no {key!r} dataset (is this a SLEAP analysis file?)")
        nodes = _decode(h5["node_names"][()])
        tracks = np.asarray(h5["tracks"][()], dtype=np.float64)
        names = _decode(h5["track_names"][()]) if "track_names" in h5 else None
        occupancy = np.asarray(h5["track_occupancy"][()]) if "track_occupancy" in h5 else None
    n_nodes = len(nodes)
    if tracks.ndim != 4:
        raise ValueError(f"{path}: 'tracks' has shape {tracks.shape}, expected 4 dimensions")
    n_tracks = len(names) if names is not None else None
    transposed = tracks.shape[1] == 2 and tracks.shape[2] == n_nodes
    plain = tracks.shape[2] == 2 and tracks.shape[1] == n_nodes
    if transposed and plain and n_tracks is not None:
        transposed = tracks.shape[0] == n_tracks
    if transposed:
        tracks = tracks.transpose(3, 2, 1, 0)  # -> (frames, nodes, 2, tracks)
    elif not plain:
        raise ValueError(
            f"{path}: 'tracks' has shape {tracks.shape}; with {n_nodes} node_names expected "
            f"(n_tracks, 2, {n_nodes}, n_frames) or (n_frames, {n_nodes}, 2, n_tracks)"
        )
    n_frames, _, _, n_tracks = tracks.shape
    if names is None:
        names = [f"track_{i}" for i in range(n_tracks)]
    if len(names) != n_tracks:
        raise ValueError(f"{path}: 'track_names' has {len(names)} names, 'tracks' has {n_tracks} tracks")
    if track is None:
        if n_tracks != 1:
            raise ValueError(f"{path}: {n_tracks} tracks ({', '.join(names)}); choose one")
        ti = 0
    elif isinstance(track, int) or (isinstance(track, str) and track.isdigit() and track not in names):
        ti = int(track)
        if not 0 <= ti < n_tracks:
            raise ValueError(f"{path}: track index {ti} out of range (0..{n_tracks - 1})")
    else:
        if track not in names:
            raise ValueError(f"{path}: no track {track!r} (tracks: {', '.join(names)})")
        ti = names.index(track)
    uv = tracks[:, :, :, ti].copy()
    if occupancy is not None:
        if occupancy.shape == (n_tracks, n_frames) and occupancy.shape != (n_frames, n_tracks):
            occupancy = occupancy.T
        if occupancy.shape != (n_frames, n_tracks):
            raise ValueError(
                f"{path}: 'track_occupancy' has shape {occupancy.shape}, expected ({n_frames}, {n_tracks})"
            )
        uv[occupancy[:, ti] == 0] = np.nan
    uv[np.isnan(uv).any(axis=2)] = np.nan
    return LabelTable(nodes, np.arange(n_frames, dtype=np.int64), uv, str(path))


# ------------------------------------------------------------------------------------------------------------
# s3k import


def _pairs(values: list[str] | None, option: str) -> dict[str, str]:
    """``["cam=FILE", ...]`` -> ``{cam: FILE}`` (error naming the option and the value)."""
    out: dict[str, str] = {}
    for value in values or []:
        cam, sep, rest = value.partition("=")
        if not sep or not cam or not rest:
            raise ValueError(f"{option} {value!r}: expected CAMERA=FILE")
        if cam in out:
            raise ValueError(f"{option}: camera {cam!r} given twice")
        out[cam] = rest
    return out


def _parse_crops(values: list[str] | None, cameras: list[str]) -> dict[str, tuple[float, ...]]:
    """``["x0,y0,x1,y1"]`` (every camera) or ``["cam=x0,y0,x1,y1", ...]`` -> ``{cam: box}``."""
    crops: dict[str, tuple[float, ...]] = {}
    for value in values or []:
        cam, sep, box_text = value.rpartition("=")
        targets = [cam] if sep else list(cameras)
        if sep and cam not in cameras:
            raise ValueError(f"--crop {value!r}: unknown camera {cam!r} (cameras: {', '.join(cameras)})")
        try:
            box = tuple(float(x) for x in box_text.split(","))
        except ValueError:
            box = ()
        if len(box) != 4 or not box[2] > box[0] or not box[3] > box[1]:
            raise ValueError(f"--crop {value!r}: expected [CAMERA=]x0,y0,x1,y1 with x1 > x0 and y1 > y0")
        for t in targets:
            crops[t] = box
    return crops


def _output_size(boxes: list[tuple[float, ...]], size: str | None, scale: float | None) -> tuple[int, int]:
    widths = {b[2] - b[0] for b in boxes}
    heights = {b[3] - b[1] for b in boxes}
    if scale is not None:
        if scale <= 0:
            raise ValueError(f"--scale must be positive, got {scale}")
        if len(widths) > 1 or len(heights) > 1:
            raise ValueError("--scale needs crops of one size; give --size W,H for crops of different sizes")
        return max(1, round(widths.pop() * scale)), max(1, round(heights.pop() * scale))
    if size is not None:
        parts = size.split(",")
        try:
            nums = [int(p) for p in parts]
        except ValueError:
            nums = []
        if len(nums) == 2 and min(nums) > 0:
            return nums[0], nums[1]
        if len(nums) == 1 and nums[0] > 0:
            # One number: the longer side, aspect ratio kept (crops must share it).
            if len({round((b[2] - b[0]) / (b[3] - b[1]), 6) for b in boxes}) > 1:
                raise ValueError("--size PX needs crops of one aspect ratio; give --size W,H")
            w, h = boxes[0][2] - boxes[0][0], boxes[0][3] - boxes[0][1]
            s = nums[0] / max(w, h)
            return max(1, round(w * s)), max(1, round(h * s))
        raise ValueError(f"--size {size!r}: expected PX (longer side) or W,H")
    if len(widths) > 1 or len(heights) > 1:
        raise ValueError("crops of different sizes need --size W,H (or --size PX) to share one image size")
    w, h = widths.pop(), heights.pop()
    if w != int(w) or h != int(h):
        raise ValueError("a crop with a fractional size needs --size")
    return int(w), int(h)


def _split_frames(
    candidates: np.ndarray, all_frames: np.ndarray, n_labelled: str, n_test: int, seed: int, stride: int
) -> dict[int, str]:
    """Random labelled / test frames among ``candidates``; the rest (every ``stride``-th) unlabelled."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(candidates)
    if n_test < 0:
        raise ValueError(f"--test must be >= 0, got {n_test}")
    if n_test > len(order):
        raise ValueError(f"--test {n_test}: only {len(order)} frames have a keypoint labelled in >= 2 views")
    test = order[:n_test]
    rest = order[n_test:]
    if str(n_labelled) == "all":
        labelled = rest
    else:
        n = int(n_labelled)
        if n < 0 or n > len(rest):
            raise ValueError(
                f"--labelled {n}: {len(rest)} frames with a keypoint labelled in >= 2 views remain after "
                f"{n_test} test frames"
            )
        labelled = rest[:n]
    splits = {int(f): "unlabelled" for f in all_frames if f % stride == 0}
    splits.update({int(f): "test" for f in test})
    splits.update({int(f): "labelled" for f in labelled})
    return dict(sorted(splits.items()))


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Convert a calibrated multi-camera recording to an s3k dataset: anipose calibration.toml, one video "
        "per camera, and 2D labels from SLEAP analysis files or DeepLabCut / Lightning Pose CSVs. Frames "
        "with labels are split into labelled and test frames (test labels are kept for evaluation); the "
        "other frames are unlabelled (their labels, if any, are not written)."
    )
    parser.add_argument("--calibration", required=True, help="anipose calibration.toml")
    parser.add_argument("--videos", nargs="+", required=True, metavar="CAM=FILE",
                        help="one video per camera; the order sets the dataset's camera order")
    labels = parser.add_mutually_exclusive_group(required=True)
    labels.add_argument("--sleap", nargs="+", metavar="CAM=FILE.h5", help="SLEAP analysis HDF5 per camera")
    labels.add_argument("--dlc", nargs="+", metavar="CAM=FILE.csv",
                        help="DeepLabCut / Lightning Pose label CSV per camera")
    labels.add_argument("--lightning-pose", metavar="DIR",
                        help="folder with Lightning Pose's multi-view CSVs CollectedData_<camera>.csv")
    parser.add_argument("--sleap-track", default=None, help="SLEAP track name or index (if several)")
    parser.add_argument("--frame-ids-from", choices=["path", "row"], default="path",
                        help="CSV frame index from the image file name's digits (default) or the row number")
    parser.add_argument("--out", required=True, help="dataset folder to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    parser.add_argument("--labelled", default="10",
                        help="number of labelled frames, or 'all' (default 10)")
    parser.add_argument("--test", type=int, default=0, help="number of test frames (default 0)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random split (default 0)")
    parser.add_argument("--stride", type=int, default=1,
                        help="keep every STRIDE-th video frame as unlabelled (default 1: all)")
    parser.add_argument("--min-views", type=int, default=2,
                        help="a frame can be labelled/test when a keypoint is labelled in this many cameras")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--size", default=None,
                      help="output image size: W,H or PX (the longer side, aspect kept)")
    size.add_argument("--scale", type=float, default=None, help="output image scale factor, e.g. 0.25")
    parser.add_argument("--crop", nargs="+", default=None, metavar="[CAM=]X0,Y0,X1,Y1",
                        help="crop box in pixel edge coordinates, for every camera or one camera")
    parser.add_argument("--units", default=None,
                        help="world length unit of the calibration (default: from the board, e.g. mm)")
    parser.add_argument("--keypoints", default=None, help="comma-separated keypoints to keep (default all)")


def import_recording(args: argparse.Namespace) -> Path:
    """Do the work of ``s3k import`` (see :func:`configure_parser` for the arguments); returns the folder."""
    from s3k.data import video
    from s3k.data.format import DatasetWriter
    from s3k.data.transforms import crop_resize_matrix, resize_crop, transform_points

    videos = _pairs(args.videos, "--videos")
    cameras = list(videos)
    calib = read_anipose_calibration(args.calibration, units=args.units)
    try:
        calib = calib.select(cameras)
    except KeyError as exc:
        raise ValueError(f"{args.calibration}: {exc.args[0]}") from None

    # Labels per camera.
    if args.sleap:
        files = _pairs(args.sleap, "--sleap")
        reader = lambda p: read_sleap_analysis(p, track=args.sleap_track)  # noqa: E731
        kind = "sleap"
    else:
        if args.dlc:
            files = _pairs(args.dlc, "--dlc")
            kind = "deeplabcut"
        else:
            files = {k: str(v) for k, v in find_lightning_pose_csvs(args.lightning_pose, cameras).items()}
            kind = "lightning-pose"
        reader = lambda p: read_dlc_csv(p, frame_ids_from=args.frame_ids_from)  # noqa: E731
    unknown = sorted(set(files) - set(cameras))
    if unknown:
        raise ValueError(
            f"labels given for cameras {unknown} that have no --videos entry ({', '.join(cameras)})"
        )
    tables = {cam: reader(path) for cam, path in files.items()}
    keypoints: list[str] = []
    for table in tables.values():
        keypoints += [k for k in table.keypoints if k not in keypoints]
    if args.keypoints:
        wanted = [k.strip() for k in args.keypoints.split(",") if k.strip()]
        missing = [k for k in wanted if k not in keypoints]
        if missing:
            raise ValueError(f"--keypoints: {missing} not in the labels ({', '.join(keypoints)})")
        keypoints = wanted

    # Videos: sizes must match the calibration, frames counted.
    counts = {}
    for c, cam in enumerate(cameras):
        W, H = video.frame_size(videos[cam])
        if (W, H) != tuple(int(v) for v in calib.size[c]):
            raise ValueError(
                f"{videos[cam]}: video is {W}x{H} but {args.calibration} gives camera {cam!r} size "
                f"{calib.size[c][0]}x{calib.size[c][1]}"
            )
        counts[cam] = video.frame_count(videos[cam])
    n_frames = min(counts.values())
    if len(set(counts.values())) > 1:
        print(f"warning: videos have different frame counts {counts}; using the first {n_frames} frames")

    # Crop and resize: one pixel map per camera, applied to K and to the labels.
    crops = _parse_crops(args.crop, cameras)
    boxes = [crops.get(cam, (0.0, 0.0, float(calib.size[c][0]), float(calib.size[c][1])))
             for c, cam in enumerate(cameras)]
    out_size = _output_size(boxes, args.size, args.scale)
    maps = [crop_resize_matrix(box, out_size) for box in boxes]
    K_out = np.stack([resize_crop(None, calib.K[c], boxes[c], out_size)[1] for c in range(len(cameras))])

    C, Kp = len(cameras), len(keypoints)
    uv = np.full((n_frames, C, Kp, 2), np.nan)
    for c, cam in enumerate(cameras):
        if cam not in tables:
            continue
        table = tables[cam]
        beyond = table.frame_ids >= n_frames
        if beyond.any():
            print(f"warning: {table.source}: {int(beyond.sum())} labelled frames beyond the video's "
                  f"{n_frames} frames are ignored")
        present = [k for k in keypoints if k in table.keypoints]
        cols = [keypoints.index(k) for k in present]
        dense = table.dense(n_frames, present)
        uv[:, c, cols] = transform_points(dense, maps[c])
    W, H = out_size
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= W - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= H - 0.5)
    outside = np.isfinite(uv).all(-1) & ~inside
    if outside.any():
        print(f"note: {int(outside.sum())} labels fall outside the (cropped) images and are dropped")
    uv[~inside] = np.nan
    mask = np.isfinite(uv).all(-1)
    views = mask.sum(axis=1)  # (F, K)
    candidates = np.flatnonzero((views >= args.min_views).any(axis=1))
    if args.stride < 1:
        raise ValueError(f"--stride must be >= 1, got {args.stride}")
    splits = _split_frames(candidates, np.arange(n_frames), args.labelled, args.test, args.seed, args.stride)

    source = {
        "importer": kind,
        "calibration": str(Path(args.calibration).resolve()),
        "videos": {cam: str(Path(p).resolve()) for cam, p in videos.items()},
        "labels": {cam: str(Path(p).resolve()) for cam, p in files.items()},
        "crop_boxes": {cam: list(b) for cam, b in zip(cameras, boxes)},
        "source_image_size": {cam: [int(v) for v in calib.size[c]] for c, cam in enumerate(cameras)},
        "split_seed": args.seed,
    }
    writer = DatasetWriter(
        args.out, keypoints, cameras, out_size, calib.units,
        calibration=(K_out, calib.dist, calib.R, calib.t), source=source,
        description=f"imported from {kind} labels and {Path(args.calibration).name}",
        overwrite=args.overwrite,
    )
    wanted = sorted(splits)
    streams = [video.iter_frames(videos[cam], wanted) for cam in cameras]
    for frames in zip(*streams):
        f = frames[0][0]
        images = []
        for c, (i, image) in enumerate(frames):
            if i != f:  # pragma: no cover - iter_frames yields the same ids for every camera
                raise RuntimeError(f"{videos[cameras[c]]}: decoded frame {i}, expected {f}")
            images.append(resize_crop(image, None, boxes[c], out_size)[0])
        split = splits[f]
        labels = (np.nan_to_num(uv[f]), mask[f]) if split != "unlabelled" else None
        writer.add_frame(f, split, np.stack(images), labels=labels, extra={"video_frame": f})
    path = writer.close()
    n = {s: sum(1 for v in splits.values() if v == s) for s in ("labelled", "test", "unlabelled")}
    n_labels = int(sum(mask[f].sum() for f, s in splits.items() if s != "unlabelled"))
    print(f"wrote {path}: {len(splits)} frames (labelled {n['labelled']}, test {n['test']}, unlabelled "
          f"{n['unlabelled']}), {C} cameras {', '.join(cameras)}, {Kp} keypoints, {W}x{H} px, "
          f"{n_labels} 2D labels, units {calib.units}")
    return path


def run(args: argparse.Namespace) -> int:
    try:
        import_recording(args)
    except (ValueError, FileNotFoundError, KeyError, IndexError) as exc:
        print(f"s3k import: error: {exc}", file=sys.stderr)
        return 1
    return 0
