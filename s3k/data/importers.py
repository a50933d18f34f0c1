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
