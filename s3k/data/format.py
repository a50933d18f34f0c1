"""The s3k dataset: a folder a person can read (``docs/dataset-format.md``), its reader and its writer.

A dataset folder holds::

    s3k.json           format name and version, keypoint and camera names, image size, units, ...
    frames.csv         frame, split (labelled / unlabelled / test), optional instance, segment, ... columns
    calibration.json   static rig: K, dist, R, t per camera            (or)
    calibration.csv    per frame: one row per (frame, camera)
    labels.csv         frame, camera, keypoint, u, v, visible (partial: any cameras, any keypoints)
    points3d.csv       frame, keypoint, x, y, z (optional ground truth, used only by evaluation)
    images/<camera>/<frame:06d>.png   (or videos/<camera>.mp4 and a video_frame column in frames.csv)

:meth:`Dataset.open` parses and validates everything except the image pixels, and raises a
:class:`DatasetError` listing every problem, each naming the file, the field and the line/frame/camera.
:func:`check_dataset` runs the same checks plus decoding every image, collecting problems instead of raising.
Images are decoded once into a uint8 cache (a memmap under ``DATASET/.cache/`` keyed by a fingerprint of the
image files, or in memory) so that random batches are memory copies.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import os
import re
import shutil
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from s3k.data.transforms import crop_resize_matrix, resize_crop, transform_points

FORMAT_NAME = "s3k-dataset"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
SPLITS = ("labelled", "unlabelled", "test")
CALIBRATION_MODES = ("static", "per_frame")

METADATA_FILE = "s3k.json"
FRAMES_FILE = "frames.csv"
STATIC_CALIBRATION_FILE = "calibration.json"
PER_FRAME_CALIBRATION_FILE = "calibration.csv"
LABELS_FILE = "labels.csv"
POINTS3D_FILE = "points3d.csv"
CACHE_DIR = ".cache"
DEFAULT_IMAGE_PATTERN = "images/{camera}/{frame:06d}.png"

FRAMES_COLUMNS = ("frame", "split")
LABELS_COLUMNS = ("frame", "camera", "keypoint", "u", "v", "visible")
POINTS3D_COLUMNS = ("frame", "keypoint", "x", "y", "z")
K_COLUMNS = tuple(f"K{i}{j}" for i in range(3) for j in range(3))
DIST_COLUMNS = ("k1", "k2", "p1", "p2", "k3")
R_COLUMNS = tuple(f"R{i}{j}" for i in range(3) for j in range(3))
T_COLUMNS = ("tx", "ty", "tz")
CALIBRATION_COLUMNS = ("frame", "camera", *K_COLUMNS, *DIST_COLUMNS, *R_COLUMNS, *T_COLUMNS)

# R is a rotation when max |R R^T - I| and |det R - 1| are below this (tolerates 6-digit rounding).
ROTATION_TOLERANCE = 1e-4
# Camera names are folder names; keypoint names are CSV cells (written unquoted) and must survive a strip().
_NAME_RE = re.compile(r"^[A-Za-z0-9_+-][A-Za-z0-9_.+-]*$")
_BAD_CELL_RE = re.compile(r"[,\"\r\n]|^\s|\s$")


# ----------------------------------------------------------------------------------------------------------
# Problems: every check reports here, naming the file, the field and where in the file.


@dataclass(frozen=True)
class Problem:
    """One finding of the checks: ``severity`` is ``"error"`` (dataset unusable) or ``"warning"``."""

    severity: str
    file: str
    field: str | None
    message: str
    line: int | None = None
    frame: int | None = None
    camera: str | None = None
    keypoint: str | None = None

    def __str__(self) -> str:
        where = self.file + (f" line {self.line}" if self.line is not None else "")
        context = [
            f"{name} {value}"
            for name, value in (("frame", self.frame), ("camera", self.camera), ("keypoint", self.keypoint))
            if value is not None
        ]
        if context:
            where += f" ({', '.join(context)})"
        field_text = f" field '{self.field}':" if self.field else ""
        return f"{where}:{field_text} {self.message}"


class DatasetError(ValueError):
    """A dataset that cannot be used; ``problems`` lists every error found (file, field, line, ...)."""

    def __init__(self, root: str | Path, problems: Sequence[Problem]):
        self.root = Path(root)
        self.problems = list(problems)
        shown = "\n".join(f"  {p}" for p in self.problems[:20])
        more = f"\n  ... and {len(self.problems) - 20} more" if len(self.problems) > 20 else ""
        super().__init__(f"dataset {self.root}: {len(self.problems)} error(s)\n{shown}{more}")


class DatasetWarning(UserWarning):
    """A problem that s3k works around (e.g. a label outside its image, which is masked)."""


class _Problems:
    def __init__(self) -> None:
        self.items: list[Problem] = []

    def error(self, file: str, field: str | None, message: str, **where: Any) -> None:
        self.items.append(Problem("error", file, field, message, **where))

    def warning(self, file: str, field: str | None, message: str, **where: Any) -> None:
        self.items.append(Problem("warning", file, field, message, **where))

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.items if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.items if p.severity == "warning"]


# ----------------------------------------------------------------------------------------------------------
# Calibration arrays and checks.


class CameraArrays(NamedTuple):
    """Calibration as numpy arrays with leading dims ``L``: ``K (*L, 3, 3)``, ``dist (*L, 5)``,
    ``R (*L, 3, 3)`` world->camera, ``t (*L, 3)`` (OpenCV: ``x_cam = R @ x_world + t``)."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray


def _as_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def camera_arrays(calibration: Any) -> CameraArrays:
    """Normalize a calibration given as ``Cameras``, a ``CameraArrays``/tuple ``(K, dist, R, t)`` or a dict
    with keys ``K, dist, R, t`` to float64 numpy arrays."""
    if isinstance(calibration, dict):
        missing = [k for k in ("K", "dist", "R", "t") if k not in calibration]
        if missing:
            raise ValueError(f"calibration dict lacks {missing}")
        parts = [calibration[k] for k in ("K", "dist", "R", "t")]
    elif isinstance(calibration, (tuple, list)) and len(calibration) == 4:
        parts = list(calibration)
    elif all(hasattr(calibration, k) for k in ("K", "dist", "R", "t")):
        parts = [calibration.K, calibration.dist, calibration.R, calibration.t]
    else:
        raise ValueError(
            "calibration must be Cameras, (K, dist, R, t) or a dict of them, "
            f"got {type(calibration).__name__}"
        )
    return CameraArrays(*(_as_numpy(p) for p in parts))


def to_cameras(arrays: CameraArrays, dtype: Any = np.float32) -> Any:
    """Wrap calibration arrays into ``s3k.geometry.Cameras`` (numpy arrays if geometry is unavailable)."""
    arrays = CameraArrays(*(np.ascontiguousarray(a, dtype=dtype) for a in arrays))
    try:
        import torch

        from s3k.geometry import Cameras
    except ImportError:
        return arrays
    torch_dtype = torch.float64 if np.dtype(dtype) == np.float64 else torch.float32
    return Cameras.from_numpy(*arrays, dtype=torch_dtype)


def _camera_defects(
    K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
) -> list[list[tuple[str, str]]]:
    """Per camera (flattened leading dims) the list of ``(field, message)`` defects."""
    n = K.shape[0]
    out: list[list[tuple[str, str]]] = [[] for _ in range(n)]
    finite = {
        "K": np.isfinite(K).all(axis=(-2, -1)),
        "dist": np.isfinite(dist).all(axis=-1),
        "R": np.isfinite(R).all(axis=(-2, -1)),
        "t": np.isfinite(t).all(axis=-1),
    }
    for name, ok in finite.items():
        for i in np.flatnonzero(~ok):
            out[i].append((name, "not finite (NaN or inf)"))
    Ks = np.where(np.isfinite(K), K, 0.0)
    last_row_err = np.abs(Ks[:, 2] - [0.0, 0.0, 1.0]).max(axis=-1)
    detK = np.linalg.det(Ks)
    for i in np.flatnonzero(finite["K"] & (last_row_err > 1e-9)):
        out[i].append(("K", f"last row must be [0, 0, 1], got {K[i, 2].tolist()}"))
    for i in np.flatnonzero(finite["K"] & (np.abs(detK) <= 1e-12)):
        out[i].append(("K", f"singular (det = {detK[i]:.3g}); focal lengths must be non-zero"))
    Rs = np.where(np.isfinite(R), R, 0.0)
    ortho = np.abs(Rs @ np.swapaxes(Rs, -1, -2) - np.eye(3)).max(axis=(-2, -1))
    detR = np.linalg.det(Rs)
    bad = finite["R"] & ((ortho > ROTATION_TOLERANCE) | (np.abs(detR - 1) > ROTATION_TOLERANCE))
    for i in np.flatnonzero(bad):
        out[i].append(
            (
                "R",
                f"not a rotation: max |R R^T - I| = {ortho[i]:.3g}, det R = {detR[i]:.6g} "
                f"(need orthonormal with det +1 within {ROTATION_TOLERANCE:g})",
            )
        )
    return out


# ----------------------------------------------------------------------------------------------------------
# Metadata and tables.


def _read_csv(root: Path, name: str, required: Sequence[str], P: _Problems) -> tuple[list[str], list] | None:
    """Rows of a CSV as ``(header, [(line, {column: text})])``; lines starting with '#' are comments."""
    path = root / name
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        P.error(name, None, "file missing")
        return None
    except (OSError, UnicodeDecodeError) as exc:
        P.error(name, None, f"cannot read: {exc}")
        return None
    header: list[str] | None = None
    rows = []
    spaced = " " in text or "\t" in text  # files s3k writes have none: skip the per-cell strip
    for line, cells in enumerate(csv.reader(io.StringIO(text)), start=1):
        if not cells or cells[0].lstrip().startswith("#"):
            continue
        if spaced:
            cells = [c.strip() for c in cells]
        if len(cells) == 1 and not cells[0]:
            continue  # a line of blanks
        if header is None:
            header = cells
            missing = [c for c in required if c not in header]
            for col in missing:
                P.error(name, col, f"required column missing from the header {header}")
            if missing:
                return None
            continue
        if len(cells) != len(header):
            P.error(name, None, f"{len(cells)} values but the header has {len(header)} columns", line=line)
            continue
        rows.append((line, dict(zip(header, cells))))
    if header is None:
        P.error(name, None, f"empty file: expected a header with columns {list(required)}")
        return None
    return header, rows


def _names(meta: dict, key: str, P: _Problems, folder_safe: bool) -> list[str] | None:
    value = meta.get(key)
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
        P.error(METADATA_FILE, key, f"must be a non-empty list of non-empty strings, got {value!r}")
        return None
    dupes = sorted({v for v in value if value.count(v) > 1})
    if dupes:
        P.error(METADATA_FILE, key, f"duplicate names {dupes}")
        return None
    bad_cells = [v for v in value if _BAD_CELL_RE.search(v)]
    if bad_cells:
        P.error(
            METADATA_FILE,
            key,
            f"names {bad_cells} must not contain commas, quotes, line breaks or leading/trailing spaces",
        )
        return None
    if folder_safe:
        bad = [v for v in value if not _NAME_RE.match(v)]
        if bad:
            P.error(
                METADATA_FILE, key, f"names {bad} must be usable as folder names (letters, digits, _ . + -)"
            )
            return None
    return list(value)


@dataclass
class _Meta:
    raw: dict
    keypoints: list[str]
    cameras: list[str]
    image_size: tuple[int, int]
    units: str
    calibration: str
    images: dict
    skeleton: list[tuple[str, str]]


def _read_metadata(root: Path, P: _Problems) -> _Meta | None:
    path = root / METADATA_FILE
    if not root.is_dir():
        P.error(str(root), None, "not a folder")
        return None
    try:
        meta = json.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        P.error(METADATA_FILE, None, "file missing: every dataset folder starts with s3k.json")
        return None
    except json.JSONDecodeError as exc:
        P.error(METADATA_FILE, None, f"not valid JSON: {exc.msg}", line=exc.lineno)
        return None
    except (OSError, UnicodeDecodeError) as exc:
        P.error(METADATA_FILE, None, f"cannot read: {exc}")
        return None
    if not isinstance(meta, dict):
        P.error(METADATA_FILE, None, "must hold a JSON object")
        return None
    n_errors = len(P.errors)
    if meta.get("format") != FORMAT_NAME:
        P.error(METADATA_FILE, "format", f"must be {FORMAT_NAME!r}, got {meta.get('format')!r}")
    version = meta.get("version")
    if isinstance(version, bool) or version not in SUPPORTED_VERSIONS:
        P.error(
            METADATA_FILE,
            "version",
            f"unsupported version {version!r}; this s3k reads version(s) {list(SUPPORTED_VERSIONS)}",
        )
    n_errors = len(P.errors)
    keypoints = _names(meta, "keypoints", P, folder_safe=False)
    cameras = _names(meta, "cameras", P, folder_safe=True)
    size = meta.get("image_size")
    if not (
        isinstance(size, list)
        and len(size) == 2
        and all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)
    ):
        P.error(METADATA_FILE, "image_size", f"must be [W, H], two positive integers, got {size!r}")
    units = meta.get("units", "m")
    if not isinstance(units, str) or not units:
        P.error(METADATA_FILE, "units", f'must be a non-empty string such as "m", got {units!r}')
    mode = meta.get("calibration")
    if mode is None:
        mode = "per_frame" if (root / PER_FRAME_CALIBRATION_FILE).exists() else "static"
    if mode not in CALIBRATION_MODES:
        P.error(METADATA_FILE, "calibration", f"must be one of {list(CALIBRATION_MODES)}, got {mode!r}")
    images = meta.get("images", {"type": "png", "pattern": DEFAULT_IMAGE_PATTERN})
    if not isinstance(images, dict) or images.get("type", "png") not in IMAGE_SOURCES:
        P.error(
            METADATA_FILE,
            "images",
            f"must be an object whose 'type' is one of {sorted(IMAGE_SOURCES)}, got {images!r}",
        )
    elif images.get("type", "png") == "png":
        pattern = images.get("pattern", DEFAULT_IMAGE_PATTERN)
        try:
            ok = isinstance(pattern, str) and pattern.format(camera="a", frame=1) != pattern.format(
                camera="b", frame=2
            )
            ok = ok and pattern.format(camera="a", frame=1) != pattern.format(camera="a", frame=2)
            ok = ok and pattern.format(camera="a", frame=1) != pattern.format(camera="b", frame=1)
        except (KeyError, IndexError, ValueError, AttributeError):
            ok = False
        if not ok:
            P.error(
                METADATA_FILE,
                "images.pattern",
                "must be a relative path that uses both {camera} and {frame} "
                f"(e.g. {DEFAULT_IMAGE_PATTERN!r}), got {pattern!r}",
            )
    skeleton: list[tuple[str, str]] = []
    raw_skeleton = meta.get("skeleton", [])
    if not isinstance(raw_skeleton, list) or not all(
        isinstance(e, list) and len(e) == 2 and all(isinstance(n, str) for n in e) for e in raw_skeleton
    ):
        P.error(
            METADATA_FILE, "skeleton", f"must be a list of [keypoint, keypoint] pairs, got {raw_skeleton!r}"
        )
    elif keypoints is not None:
        for a, b in raw_skeleton:
            for n in (a, b):
                if n not in keypoints:
                    P.error(METADATA_FILE, "skeleton", f"unknown keypoint {n!r}; keypoints are {keypoints}")
            skeleton.append((a, b))
    if len(P.errors) > n_errors:
        return None
    assert keypoints is not None and cameras is not None and size is not None  # else errors were recorded
    return _Meta(meta, keypoints, cameras, (size[0], size[1]), units, mode, dict(images), skeleton)


def _parse_int(text: str) -> int | None:
    try:
        return int(text)
    except ValueError:
        return None


def _parse_float(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


@dataclass
class _Frames:
    ids: np.ndarray  # (N,) int64, file order
    splits: np.ndarray  # (N,) str
    columns: dict[str, np.ndarray]  # extra columns, as text
    lines: np.ndarray  # (N,) line numbers in frames.csv
    row_of: dict[int, int]


def _read_frames(root: Path, P: _Problems) -> _Frames | None:
    table = _read_csv(root, FRAMES_FILE, FRAMES_COLUMNS, P)
    if table is None:
        return None
    header, rows = table
    ids: list[int] = []
    splits: list[str] = []
    lines: list[int] = []
    extra: dict[str, list[str]] = {c: [] for c in header if c not in FRAMES_COLUMNS}
    seen: dict[int, int] = {}
    for line, row in rows:
        frame = _parse_int(row["frame"])
        if frame is None or frame < 0:
            P.error(FRAMES_FILE, "frame", f"must be a non-negative integer, got {row['frame']!r}", line=line)
            continue
        if frame in seen:
            P.error(FRAMES_FILE, "frame", f"frame {frame} repeated (first on line {seen[frame]})", line=line)
            continue
        if row["split"] not in SPLITS:
            P.error(
                FRAMES_FILE,
                "split",
                f"unknown split {row['split']!r}; use one of {list(SPLITS)}",
                line=line,
                frame=frame,
            )
            continue
        seen[frame] = line
        ids.append(frame)
        splits.append(row["split"])
        lines.append(line)
        for c in extra:
            extra[c].append(row[c])
    if not rows:
        P.error(FRAMES_FILE, None, "no frames listed")
    if "video_frame" in extra:
        for line, frame, text in zip(lines, ids, extra["video_frame"]):
            value = _parse_int(text)
            if value is None or value < 0:
                P.error(
                    FRAMES_FILE,
                    "video_frame",
                    f"must be a non-negative integer, got {text!r}",
                    line=line,
                    frame=frame,
                )
    return _Frames(
        np.asarray(ids, dtype=np.int64),
        np.asarray(splits, dtype=object),
        {c: np.asarray(v, dtype=object) for c, v in extra.items()},
        np.asarray(lines, dtype=np.int64),
        {f: i for i, f in enumerate(ids)},
    )


def _read_static_calibration(root: Path, meta: _Meta, P: _Problems) -> CameraArrays | None:
    name = STATIC_CALIBRATION_FILE
    try:
        data = json.loads((root / name).read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        P.error(name, None, "file missing (s3k.json says calibration is static)")
        return None
    except json.JSONDecodeError as exc:
        P.error(name, None, f"not valid JSON: {exc.msg}", line=exc.lineno)
        return None
    except (OSError, UnicodeDecodeError) as exc:
        P.error(name, None, f"cannot read: {exc}")
        return None
    cams = data.get("cameras") if isinstance(data, dict) else None
    if not isinstance(cams, dict):
        P.error(name, "cameras", "must be an object mapping each camera name to {K, dist, R, t}")
        return None
    for extra in sorted(set(cams) - set(meta.cameras)):
        P.error(
            name,
            f"cameras.{extra}",
            f"unknown camera {extra!r}; s3k.json cameras are {meta.cameras}",
            camera=extra,
        )
    C = len(meta.cameras)
    K, dist = np.full((C, 3, 3), np.nan), np.full((C, 5), np.nan)
    R, t = np.full((C, 3, 3), np.nan), np.full((C, 3), np.nan)
    ok = True
    unparsed: set[tuple[int, str]] = set()
    shapes = {"K": (3, 3), "dist": (5,), "R": (3, 3), "t": (3,)}
    for c, cam in enumerate(meta.cameras):
        entry = cams.get(cam)
        if not isinstance(entry, dict):
            P.error(
                name, f"cameras.{cam}", "missing: every camera of s3k.json needs K, dist, R, t", camera=cam
            )
            ok = False
            continue
        for key, target in (("K", K), ("dist", dist), ("R", R), ("t", t)):
            try:
                value = np.asarray(entry.get(key), dtype=np.float64)
            except (TypeError, ValueError):
                value = None
            if value is None or value.shape != shapes[key]:
                got = entry.get(key)
                P.error(
                    name,
                    f"cameras.{cam}.{key}",
                    f"must be numbers of shape {shapes[key]}, got {got!r}",
                    camera=cam,
                )
                unparsed.add((c, key))
                ok = False
                continue
            target[c] = value
    defects = _camera_defects(K, dist, R, t)
    for c, cam in enumerate(meta.cameras):
        if not isinstance(cams.get(cam), dict):
            continue
        for fld, message in defects[c]:
            if (c, fld) not in unparsed:
                P.error(name, f"cameras.{cam}.{fld}", message, camera=cam)
                ok = False
    return CameraArrays(K, dist, R, t) if ok else None


def _read_per_frame_calibration(
    root: Path, meta: _Meta, frames: _Frames, P: _Problems
) -> CameraArrays | None:
    name = PER_FRAME_CALIBRATION_FILE
    table = _read_csv(root, name, CALIBRATION_COLUMNS, P)
    if table is None:
        return None
    _, rows = table
    N, C = len(frames.ids), len(meta.cameras)
    values = np.full((N, C, 26), np.nan)
    lines = np.zeros((N, C), dtype=np.int64)
    cam_index = {c: i for i, c in enumerate(meta.cameras)}
    numeric = CALIBRATION_COLUMNS[2:]
    n_errors = len(P.errors)
    try:  # fast path: numpy converts every number at once; any bad cell sends us to the per-cell messages
        parsed = np.array([[row[col] for col in numeric] for _, row in rows], dtype=np.float64)
    except ValueError:
        parsed = None
    for r, (line, row) in enumerate(rows):
        frame = _parse_int(row["frame"])
        if frame is None or frame not in frames.row_of:
            P.error(name, "frame", f"frame {row['frame']!r} is not listed in {FRAMES_FILE}", line=line)
            continue
        c = cam_index.get(row["camera"])
        if c is None:
            P.error(
                name,
                "camera",
                f"unknown camera {row['camera']!r}; s3k.json cameras are {meta.cameras}",
                line=line,
                frame=frame,
            )
            continue
        i = frames.row_of[frame]
        if lines[i, c]:
            P.error(
                name,
                None,
                f"second row for this frame and camera (first on line {lines[i, c]})",
                line=line,
                frame=frame,
                camera=row["camera"],
            )
            continue
        lines[i, c] = line
        if parsed is not None:
            values[i, c] = parsed[r]
            continue
        for j, col in enumerate(numeric):
            value = _parse_float(row[col])
            if value is None:
                P.error(
                    name, col, f"not a number: {row[col]!r}", line=line, frame=frame, camera=row["camera"]
                )
            else:
                values[i, c, j] = value
    for i, c in zip(*np.nonzero(lines == 0)):
        P.error(
            name,
            None,
            "no calibration row for this frame and camera",
            frame=int(frames.ids[i]),
            camera=meta.cameras[c],
        )
    K = values[..., 0:9].reshape(N, C, 3, 3)
    dist = values[..., 9:14]
    R = values[..., 14:23].reshape(N, C, 3, 3)
    t = values[..., 23:26]
    present = (lines > 0).reshape(-1)
    defects = _camera_defects(K.reshape(-1, 3, 3), dist.reshape(-1, 5), R.reshape(-1, 3, 3), t.reshape(-1, 3))
    column_of = {"K": "K00..K22", "dist": "k1..k3", "R": "R00..R22", "t": "tx..tz"}
    for flat, found in enumerate(defects):
        if not present[flat]:
            continue
        i, c = divmod(flat, C)
        for fld, message in found:
            # A value that failed to parse was already reported; don't report its NaN again.
            P.error(
                name,
                column_of[fld],
                message,
                line=int(lines[i, c]),
                frame=int(frames.ids[i]),
                camera=meta.cameras[c],
            )
    if len(P.errors) > n_errors:
        return None
    return CameraArrays(K, dist, R, t)


@dataclass
class _Labels:
    uv: np.ndarray  # (N, C, K, 2) float64, NaN where absent
    present: np.ndarray  # (N, C, K) a row exists
    visible: np.ndarray  # (N, C, K) visible == 1
    inside: np.ndarray  # (N, C, K) (u, v) within the image


def _read_labels(root: Path, meta: _Meta, frames: _Frames, P: _Problems) -> _Labels:
    N, C, Kp = len(frames.ids), len(meta.cameras), len(meta.keypoints)
    labels = _Labels(
        np.full((N, C, Kp, 2), np.nan),
        np.zeros((N, C, Kp), bool),
        np.zeros((N, C, Kp), bool),
        np.zeros((N, C, Kp), bool),
    )
    name = LABELS_FILE
    if not (root / name).exists():
        return labels
    table = _read_csv(root, name, LABELS_COLUMNS[:5], P)
    if table is None:
        return labels
    _, rows = table
    cam_index = {c: i for i, c in enumerate(meta.cameras)}
    kp_index = {k: i for i, k in enumerate(meta.keypoints)}
    W, H = meta.image_size
    first_line: dict[tuple[int, int, int], int] = {}
    for line, row in rows:
        frame = _parse_int(row["frame"])
        where = {"line": line, "frame": frame if frame is not None else row["frame"]}
        if frame is None or frame not in frames.row_of:
            P.error(name, "frame", f"frame {row['frame']!r} is not listed in {FRAMES_FILE}", **where)
            continue
        c, k = cam_index.get(row["camera"]), kp_index.get(row["keypoint"])
        bad = False
        if c is None:
            P.error(
                name,
                "camera",
                f"unknown camera {row['camera']!r}; s3k.json cameras are {meta.cameras}",
                **where,
            )
            bad = True
        if k is None:
            P.error(
                name,
                "keypoint",
                f"unknown keypoint {row['keypoint']!r}; s3k.json keypoints are {meta.keypoints}",
                **where,
            )
            bad = True
        if bad:
            continue
        where.update(camera=row["camera"], keypoint=row["keypoint"])
        vis_text = row.get("visible", "1") or "1"
        if vis_text.lower() in ("1", "true"):
            visible = True
        elif vis_text.lower() in ("0", "false"):
            visible = False
        else:
            P.error(name, "visible", f"must be 1 or 0, got {vis_text!r}", **where)
            continue
        uv = []
        for col in ("u", "v"):
            text = row[col]
            value = _parse_float(text) if text else (np.nan if not visible else None)
            if value is None or (visible and not np.isfinite(value)):
                P.error(
                    name,
                    col,
                    f"must be a finite number (empty only when visible is 0), got {text!r}",
                    **where,
                )
                break
            uv.append(value)
        if len(uv) < 2:
            continue
        assert c is not None and k is not None
        i = frames.row_of[frame]
        key = (i, c, k)
        if key in first_line:
            P.error(
                name, None, f"keypoint labelled twice in this view (first on line {first_line[key]})", **where
            )
            continue
        first_line[key] = line
        labels.uv[i, c, k] = uv
        labels.present[i, c, k] = True
        labels.visible[i, c, k] = visible
        u, v = uv
        inside = -0.5 <= u <= W - 0.5 and -0.5 <= v <= H - 0.5
        labels.inside[i, c, k] = inside
        if visible and not inside:
            fld = "u" if not -0.5 <= u <= W - 0.5 else "v"
            P.warning(
                name,
                fld,
                f"label ({u:g}, {v:g}) is outside the {W}x{H} image "
                f"([-0.5, {W - 0.5}] x [-0.5, {H - 0.5}]); it is masked",
                **where,
            )
    return labels


def _read_points3d(root: Path, meta: _Meta, frames: _Frames, P: _Problems) -> np.ndarray | None:
    name = POINTS3D_FILE
    if not (root / name).exists():
        return None
    table = _read_csv(root, name, POINTS3D_COLUMNS, P)
    if table is None:
        return None
    _, rows = table
    kp_index = {k: i for i, k in enumerate(meta.keypoints)}
    X = np.full((len(frames.ids), len(meta.keypoints), 3), np.nan)
    first_line: dict[tuple[int, int], int] = {}
    for line, row in rows:
        frame = _parse_int(row["frame"])
        if frame is None or frame not in frames.row_of:
            P.error(name, "frame", f"frame {row['frame']!r} is not listed in {FRAMES_FILE}", line=line)
            continue
        k = kp_index.get(row["keypoint"])
        if k is None:
            P.error(
                name,
                "keypoint",
                f"unknown keypoint {row['keypoint']!r}; s3k.json keypoints are {meta.keypoints}",
                line=line,
                frame=frame,
            )
            continue
        where = {"line": line, "frame": frame, "keypoint": row["keypoint"]}
        xyz = [_parse_float(row[c]) for c in "xyz"]
        bad = [c for c, value in zip("xyz", xyz) if value is None or not np.isfinite(value)]
        if bad:
            P.error(name, bad[0], f"must be a finite number, got {row[bad[0]]!r}", **where)
            continue
        i = frames.row_of[frame]
        if (i, k) in first_line:
            P.error(name, None, f"point given twice (first on line {first_line[(i, k)]})", **where)
            continue
        first_line[(i, k)] = line
        X[i, k] = xyz
    return X


# ----------------------------------------------------------------------------------------------------------
# Image sources: PNG files per camera per frame, or one video per camera. Other sources register here.


def decode_image(path: str | Path) -> np.ndarray:
    """Decode an image file to ``uint8 (H, W, 3)`` RGB; a ``ValueError`` names the file when unreadable."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise ValueError(f"{path}: cannot decode as an image (truncated or not an image file)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


@contextlib.contextmanager
def _file_lock(f):
    """Exclusive advisory lock on an open file (POSIX); a no-op where fcntl is unavailable."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    fcntl.flock(f.fileno(), fcntl.LOCK_EX)
    try:
        yield
    finally:
        fcntl.flock(f.fileno(), fcntl.LOCK_UN)


class PngImages:
    """One image file per camera per frame at ``pattern`` (default ``images/{camera}/{frame:06d}.png``)."""

    random_access = True

    def __init__(self, root: Path, spec: dict, cameras: list[str], frame_ids: np.ndarray, columns: dict):
        self.root = root
        self.pattern = spec.get("pattern", DEFAULT_IMAGE_PATTERN)
        self.cameras = cameras

    def relpath(self, frame: int, camera: str) -> str:
        return self.pattern.format(camera=camera, frame=int(frame))

    def check(self, frame_ids: np.ndarray, P: _Problems) -> list[str]:
        """Report missing files; returns fingerprint items (path, size, mtime)."""
        items = []
        root = str(self.root)
        for frame in frame_ids:
            for cam in self.cameras:
                rel = self.relpath(frame, cam)
                try:
                    st = os.stat(os.path.join(root, rel))
                except OSError:
                    P.error(rel, "image", "image file missing", frame=int(frame), camera=cam)
                    continue
                items.append(f"{rel}:{st.st_size}:{st.st_mtime_ns}")
        return items

    def read_rows(self, frame_ids: Sequence[int], workers: int) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(index into frame_ids, camera index, image (H, W, 3) uint8)`` for every requested image."""
        jobs = [(i, c) for i in range(len(frame_ids)) for c in range(len(self.cameras))]

        def load(job):
            i, c = job
            return i, c, decode_image(self.root / self.relpath(frame_ids[i], self.cameras[c]))

        if workers <= 1 or len(jobs) <= 1:
            yield from map(load, jobs)
            return
        with ThreadPoolExecutor(max_workers=workers) as pool:  # cv2 decodes without holding the GIL
            yield from pool.map(load, jobs)

    def describe(self, frame: int, c: int) -> str:
        return self.relpath(frame, self.cameras[c])


class VideoImages:
    """One video per camera (``spec["videos"][camera]``, relative paths); frame ``f`` is video frame
    ``video_frame`` from frames.csv (the frame id itself when that column is absent)."""

    random_access = False

    def __init__(self, root: Path, spec: dict, cameras: list[str], frame_ids: np.ndarray, columns: dict):
        self.root = root
        self.videos = spec.get("videos", {})
        self.cameras = cameras
        index = columns.get("video_frame")
        self.video_frame = {
            int(f): (int(index[i]) if index is not None and str(index[i]).lstrip("-").isdigit() else int(f))
            for i, f in enumerate(frame_ids)
        }

    def check(self, frame_ids: np.ndarray, P: _Problems) -> list[str]:
        items: list[str] = []
        if not isinstance(self.videos, dict):
            P.error(METADATA_FILE, "images.videos", "must map each camera name to a video file")
            return items
        for cam in self.cameras:
            rel = self.videos.get(cam)
            if not isinstance(rel, str):
                P.error(
                    METADATA_FILE, f"images.videos.{cam}", "no video file given for this camera", camera=cam
                )
                continue
            try:
                st = os.stat(self.root / rel)
            except OSError:
                P.error(rel, "video", "video file missing", camera=cam)
                continue
            items.append(f"{rel}:{st.st_size}:{st.st_mtime_ns}")
        for cam in sorted(set(self.videos) - set(self.cameras)):
            P.error(METADATA_FILE, f"images.videos.{cam}", f"unknown camera {cam!r}", camera=cam)
        return items

    def read_rows(self, frame_ids: Sequence[int], workers: int) -> Iterator[tuple[int, int, np.ndarray]]:
        wanted = [self.video_frame[int(f)] for f in frame_ids]
        for c, cam in enumerate(self.cameras):
            path = self.root / self.videos[cam]
            images = dict(_iter_video(path, sorted(set(wanted))))
            for i, index in enumerate(wanted):
                if index not in images:
                    raise ValueError(f"{self.videos[cam]}: frame {index} not found (frame {frame_ids[i]})")
                yield i, c, images[index]

    def describe(self, frame: int, c: int) -> str:
        return f"{self.videos.get(self.cameras[c])} frame {self.video_frame.get(int(frame))}"


def _iter_video(path: Path, indices: list[int]) -> Iterator[tuple[int, np.ndarray]]:
    """Decode frames ``indices`` of a video (RGB uint8) in one front-to-back pass (``s3k.data.video``)."""
    from s3k.data.video import iter_frames

    try:
        yield from iter_frames(path, indices)
    except IndexError as exc:  # a frame index beyond the video's end
        raise ValueError(str(exc)) from exc


IMAGE_SOURCES: dict[str, Callable[..., Any]] = {"png": PngImages, "video": VideoImages}


def register_image_source(type_name: str, factory: Callable[..., Any]) -> None:
    """Make ``{"images": {"type": type_name, ...}}`` in s3k.json read through ``factory``.

    ``factory(root, spec, cameras, frame_ids, columns)`` returns an object with ``check(frame_ids, problems)``
    (reports missing files, returns fingerprint strings), ``read_rows(frame_ids, workers)`` (yields
    ``(i, camera_index, uint8 (H, W, 3) RGB)``) and ``describe(frame, camera_index)`` (text naming the file);
    a class attribute ``random_access = False`` makes the loader decode all frames in one pass on first use.
    """
    IMAGE_SOURCES[type_name] = factory


# ----------------------------------------------------------------------------------------------------------
# Parsing a whole folder.


@dataclass
class _Contents:
    root: Path
    meta: _Meta
    frames: _Frames
    calibration: CameraArrays  # (C, ...) static or (N, C, ...) per frame
    labels: _Labels
    points3d: np.ndarray | None
    source: Any
    fingerprint_items: list[str] = field(default_factory=list)


def _parse(root: Path, P: _Problems) -> _Contents | None:
    meta = _read_metadata(root, P)
    if meta is None:
        return None
    frames = _read_frames(root, P)
    if frames is None:
        return None
    if meta.calibration == "static":
        calib = _read_static_calibration(root, meta, P)
    else:
        calib = _read_per_frame_calibration(root, meta, frames, P)
    labels = _read_labels(root, meta, frames, P)
    points = _read_points3d(root, meta, frames, P)
    spec = meta.images
    source = IMAGE_SOURCES[spec.get("type", "png")](root, spec, meta.cameras, frames.ids, frames.columns)
    items = source.check(frames.ids, P)
    if calib is None:
        # Reported already; a NaN placeholder lets check_dataset go on to the images and the summary.
        lead = (len(meta.cameras),) if meta.calibration == "static" else (len(frames.ids), len(meta.cameras))
        calib = CameraArrays(*(np.full((*lead, *s), np.nan) for s in ((3, 3), (5,), (3, 3), (3,))))
    return _Contents(root, meta, frames, calib, labels, points, source, items)


def check_dataset(
    path: str | Path, check_images: bool = True, workers: int | None = None
) -> tuple[list[Problem], Dataset | None]:
    """Run every check on a dataset folder, collecting problems instead of stopping at the first.

    Args:
        path: dataset folder.
        check_images: also decode every image and check its size against ``image_size``.
        workers: decoding threads (default: number of CPUs).

    Returns:
        ``(problems, dataset)``: all problems found (errors and warnings) and the dataset when its tables
        could be parsed (None otherwise; a dataset with image errors is still returned for its summary).
    """
    root = Path(path)
    P = _Problems()
    contents = _parse(root, P)
    if contents is None:
        return P.items, None
    dataset = Dataset(contents, cache="none", workers=workers)
    lines = contents.frames.lines
    labelled = np.flatnonzero(contents.frames.splits == "labelled")
    seen_twice = (dataset._label_mask[labelled].sum(1) >= 2).any(-1)
    for row in labelled[~seen_twice]:
        P.warning(
            FRAMES_FILE,
            "split",
            "labelled frame without any keypoint labelled in 2 or more cameras: the "
            "supervised loss cannot triangulate it",
            line=int(lines[row]),
            frame=int(contents.frames.ids[row]),
        )
    if check_images and not P.errors:
        dataset._check_all_images(P)
    elif check_images:
        # Tables have errors; still report unreadable images among the files that exist.
        dataset._check_all_images(P, only_existing=True)
    return P.items, dataset


# ----------------------------------------------------------------------------------------------------------
# The dataset.


class Dataset:
    """A validated dataset folder. Create with :meth:`Dataset.open`.

    Attributes:
        path: the folder.
        keypoints: keypoint names (``K`` of them).
        cameras: camera names (``C``).
        image_size: ``(W, H)`` of the images this object returns (after any resize/crop on open).
        source_image_size: ``(W, H)`` of the stored images.
        units: world units of calibration and 3D points (``"m"`` unless the rig says otherwise).
        static_calibration: True when one calibration serves every frame.
        frame_ids: ``(N,)`` int64 frame ids in file order.
        skeleton: pairs of keypoint names (may be empty); ``metadata``: the raw s3k.json.
    """

    def __init__(
        self,
        contents: _Contents,
        image_size=None,
        crop_box=None,
        cache: str = "disk",
        workers: int | None = None,
    ):
        self._c = contents
        meta = contents.meta
        self.path = contents.root
        self.metadata = meta.raw
        self.keypoints = list(meta.keypoints)
        self.cameras = list(meta.cameras)
        self.units = meta.units
        self.skeleton = list(meta.skeleton)
        self.description = meta.raw.get("description")
        self.source = meta.raw.get("source")
        self.static_calibration = meta.calibration == "static"
        self.source_image_size = meta.image_size
        self.frame_ids = contents.frames.ids.copy()
        self.frame_columns = dict(contents.frames.columns)
        W, H = meta.image_size
        self._resample = crop_box is not None or (image_size is not None and tuple(image_size) != (W, H))
        box = (0, 0, W, H) if crop_box is None else tuple(crop_box)
        if image_size is None:
            image_size = (int(box[2] - box[0]), int(box[3] - box[1]))
        self.crop_box = box
        self.image_size = (int(image_size[0]), int(image_size[1]))
        # M maps stored-image pixels to returned-image pixels; K' = M K (transforms.resize_crop).
        self.pixel_map = crop_resize_matrix(box, self.image_size)
        self._workers = workers or min(8, os.cpu_count() or 1)
        if cache not in ("disk", "memory", "none"):
            raise ValueError(f"cache must be 'disk', 'memory' or 'none', got {cache!r}")
        self._cache_mode = cache
        self._cache: Any = None  # (N, C, H, W, 3) uint8 array or memmap, created on first use
        self._filled: Any = None  # (N,) uint8, 1 where a frame is decoded
        self._lock = threading.Lock()
        self._sorted = np.argsort(self.frame_ids, kind="stable")

        labels = contents.labels
        uv = transform_points(labels.uv, self.pixel_map)
        w, h = self.image_size
        inside_new = (
            (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= h - 0.5)
        )
        self._label_mask = labels.present & labels.visible & labels.inside & inside_new
        self._label_uv = np.where(self._label_mask[..., None], uv, 0.0)

    # -- construction ------------------------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        path: str | Path,
        image_size: Sequence[int] | None = None,
        crop_box: Sequence[float] | None = None,
        cache: str = "disk",
        workers: int | None = None,
    ) -> Dataset:
        """Open and validate a dataset folder (all tables; image files must exist, pixels are checked on
        decode or by ``s3k validate``).

        Args:
            path: dataset folder.
            image_size: ``(W, H)`` to resize images to on load; intrinsics and labels follow exactly.
            crop_box: ``(x0, y0, x1, y1)`` region of the stored images (pixel edge coordinates) to keep.
            cache: ``"disk"`` (uint8 memmap under ``DATASET/.cache/``, shared by processes and runs; falls
                back to memory if the folder is read-only), ``"memory"``, or ``"none"`` (decode every call).
            workers: image decoding threads.

        Raises:
            DatasetError: listing every problem, each naming the file, the field and the line/frame/camera.
        """
        P = _Problems()
        contents = _parse(Path(path), P)
        if P.errors or contents is None:
            raise DatasetError(path, P.errors)
        outside = [p for p in P.warnings]
        if outside:
            shown = "; ".join(str(p) for p in outside[:5])
            more = f" (and {len(outside) - 5} more)" if len(outside) > 5 else ""
            warnings.warn(f"dataset {path}: {shown}{more}", DatasetWarning, stacklevel=2)
        return cls(contents, image_size=image_size, crop_box=crop_box, cache=cache, workers=workers)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __repr__(self) -> str:
        counts = ", ".join(f"{s} {len(self.frames(s))}" for s in SPLITS)
        return (
            f"Dataset({str(self.path)!r}, {len(self)} frames ({counts}), cameras {self.cameras}, "
            f"keypoints {self.keypoints}, image_size {self.image_size})"
        )

    # -- tables ------------------------------------------------------------------------------------------

    def frames(self, split: str | None = None) -> np.ndarray:
        """Frame ids ``(N,)`` of a split (``"labelled" | "unlabelled" | "test"``), or all when None."""
        if split is None:
            return self.frame_ids.copy()
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; use one of {list(SPLITS)}")
        return self.frame_ids[self._c.frames.splits == split]

    def split_of(self, frame_ids) -> np.ndarray:
        """Split name of each frame id."""
        return self._c.frames.splits[self._rows(frame_ids)]

    def column(self, name: str, frame_ids=None) -> np.ndarray:
        """An extra frames.csv column (e.g. ``instance``, ``segment``) as text, for ``frame_ids`` or all."""
        if name not in self.frame_columns:
            raise KeyError(f"{FRAMES_FILE} has no column {name!r}; columns: {sorted(self.frame_columns)}")
        values = self.frame_columns[name]
        return values if frame_ids is None else values[self._rows(frame_ids)]

    def _rows(self, frame_ids) -> np.ndarray:
        ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        pos = np.searchsorted(self.frame_ids, ids, sorter=self._sorted)
        pos = np.clip(pos, 0, len(self.frame_ids) - 1)
        rows = self._sorted[pos]
        bad = self.frame_ids[rows] != ids
        if bad.any():
            raise KeyError(f"frame ids {ids[bad][:10].tolist()} are not in {self.path / FRAMES_FILE}")
        return rows

    def calibration_arrays(self, frame_ids, dtype: Any = np.float64) -> CameraArrays:
        """Calibration of ``frame_ids`` as numpy ``CameraArrays`` with leading dims ``(B, C)``, intrinsics of
        the returned images (after resize/crop)."""
        rows = self._rows(frame_ids)
        cal = self._c.calibration
        if self.static_calibration:
            parts = [np.broadcast_to(a, (len(rows), *a.shape)) for a in cal]
        else:
            parts = [a[rows] for a in cal]
        K, dist, R, t = parts
        K = self.pixel_map @ K
        return CameraArrays(*(np.array(a, dtype=dtype) for a in (K, dist, R, t)))

    def calibration(self, frame_ids, dtype: Any = np.float32):
        """``Cameras`` with leading dims ``(B, C)`` for ``frame_ids`` (intrinsics of the returned images)."""
        return to_cameras(self.calibration_arrays(frame_ids), dtype=dtype)

    def rig(self, dtype: Any = np.float32):
        """``Cameras (C,)`` of a static rig; raises ``ValueError`` when calibration is per frame."""
        if not self.static_calibration:
            raise ValueError(f"{self.path}: calibration is per frame; use calibration(frame_ids)")
        K, dist, R, t = self._c.calibration
        return to_cameras(CameraArrays(self.pixel_map @ K, dist, R, t), dtype=dtype)

    def labels(self, frame_ids) -> tuple[np.ndarray, np.ndarray]:
        """2D labels of ``frame_ids``: ``uv (B, C, K, 2) float32`` (pixels of the returned images, 0 where
        masked) and ``mask (B, C, K) bool`` (labelled, visible, inside the image)."""
        rows = self._rows(frame_ids)
        return self._label_uv[rows].astype(np.float32), self._label_mask[rows].copy()

    def points3d(self, frame_ids) -> tuple[np.ndarray, np.ndarray] | None:
        """Ground-truth 3D ``(X (B, K, 3) float32, mask (B, K) bool)`` in dataset units, or None when the
        dataset has none. For evaluation only."""
        X = self._c.points3d
        if X is None:
            return None
        rows = self._rows(frame_ids)
        sel = X[rows]
        mask = np.isfinite(sel).all(-1)
        return np.where(mask[..., None], sel, 0.0).astype(np.float32), mask

    @property
    def has_points3d(self) -> bool:
        return self._c.points3d is not None

    # -- images ------------------------------------------------------------------------------------------

    def _fingerprint(self) -> str:
        h = hashlib.sha1()
        h.update(
            json.dumps(
                [
                    FORMAT_VERSION,
                    list(self.crop_box),
                    list(self.image_size),
                    self.cameras,
                    self.frame_ids.tolist(),
                ]
            ).encode()
        )
        for item in self._c.fingerprint_items:
            h.update(item.encode())
        return h.hexdigest()[:16]

    def _ensure_cache(self) -> None:
        if self._cache is not None or self._cache_mode == "none":
            return
        W, H = self.image_size
        shape = (len(self), len(self.cameras), H, W, 3)
        if self._cache_mode == "disk":
            name = f"images-{self._fingerprint()}-{W}x{H}"
            failures = []
            for folder in self._cache_folders():
                try:
                    self._open_disk_cache(folder / name, shape)
                    return
                except OSError as exc:
                    failures.append(f"{folder}: {exc}")
            warnings.warn(
                f"cannot write the image cache ({'; '.join(failures)}); caching in memory instead",
                DatasetWarning,
                stacklevel=3,
            )
        self._cache = np.zeros(shape, dtype=np.uint8)  # pages are allocated on first write
        self._filled = np.zeros(len(self), dtype=np.uint8)

    def _cache_folders(self) -> list[Path]:
        """Where the disk cache may live: ``$S3K_CACHE_DIR`` if set, else ``DATASET/.cache`` and, for
        read-only datasets, the user's cache folder (file names there include a hash of the dataset path)."""
        tag = hashlib.sha1(str(self.path.resolve()).encode()).hexdigest()[:8]
        if os.environ.get("S3K_CACHE_DIR"):
            return [Path(os.environ["S3K_CACHE_DIR"]) / tag]
        user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "s3k" / tag
        return [self.path / CACHE_DIR, user]

    def _open_disk_cache(self, base: Path, shape: tuple[int, ...]) -> None:
        base.parent.mkdir(parents=True, exist_ok=True)
        data_path, flag_path = base.with_suffix(".u8"), base.with_suffix(".filled")
        # Processes sharing the cache (DDP ranks, parallel runs) must not both create it: one truncating the
        # file another already writes to would leave frames flagged as decoded but black.
        with open(base.with_suffix(".lock"), "a") as lock, _file_lock(lock):
            sizes = {data_path: int(np.prod(shape)), flag_path: len(self)}
            if not all(p.exists() and p.stat().st_size == n for p, n in sizes.items()):
                for p, n in sizes.items():
                    with open(p, "wb") as f:
                        f.truncate(n)  # sparse: disk is used as frames are decoded
            self._filled = np.memmap(flag_path, dtype=np.uint8, mode="r+", shape=(len(self),))
            self._cache = np.memmap(data_path, dtype=np.uint8, mode="r+", shape=shape)

    def _decode_into(self, rows: np.ndarray, out: np.ndarray, out_rows: np.ndarray | None = None) -> None:
        """Decode frames ``rows`` (all cameras) into ``out[out_rows]`` (default ``out[:len(rows)]``) of shape
        ``(*, C, H, W, 3)``, checking sizes."""
        W, H = self.source_image_size
        ids = self.frame_ids[rows]
        source = self._c.source
        for i, c, image in source.read_rows(ids, self._workers):
            if image.shape != (H, W, 3):
                raise DatasetError(
                    self.path,
                    [
                        Problem(
                            "error",
                            source.describe(ids[i], c),
                            "size",
                            f"image is {image.shape[1]}x{image.shape[0]}, s3k.json image_size is {W}x{H}",
                            frame=int(ids[i]),
                            camera=self.cameras[c],
                        )
                    ],
                )
            if self._resample:
                image, _ = resize_crop(image, None, self.crop_box, self.image_size)
            out[i if out_rows is None else out_rows[i], c] = image

    def _decode_rows(self, rows: np.ndarray, out: np.ndarray, out_rows: np.ndarray | None = None) -> None:
        try:
            self._decode_into(rows, out, out_rows)
        except DatasetError:
            raise
        except ValueError as exc:
            raise DatasetError(
                self.path, [Problem("error", str(exc).split(":")[0], "image", str(exc))]
            ) from exc

    def preload(self, split: str | None = None, chunk: int = 256) -> None:
        """Decode every image of ``split`` (all when None) into the cache now, in parallel."""
        self._ensure_cache()
        if self._cache is None:
            return
        rows = self._rows(self.frames(split))
        missing = rows[self._filled[rows] == 0]
        if not getattr(self._c.source, "random_access", True):
            chunk = max(1, len(missing))  # a video is decoded front to back: one pass for everything
        for start in range(0, len(missing), chunk):
            self._fill(missing[start : start + chunk])

    def _fill(self, rows: np.ndarray) -> None:
        with self._lock:
            rows = rows[self._filled[rows] == 0]
            if not len(rows):
                return
            self._decode_rows(rows, self._cache, out_rows=rows)
            if isinstance(self._cache, np.memmap):
                self._cache.flush()
            self._filled[rows] = 1  # only after the pixels are written, for other processes sharing the file

    def images(self, frame_ids) -> np.ndarray:
        """Images of ``frame_ids`` as ``uint8 (B, C, H, W, 3)`` RGB (``(W, H) = image_size``).

        The first request of a frame decodes it into the cache; later requests copy from memory.
        """
        rows = self._rows(frame_ids)
        self._ensure_cache()
        if self._cache is None:
            W, H = self.image_size
            out = np.empty((len(rows), len(self.cameras), H, W, 3), dtype=np.uint8)
            self._decode_rows(rows, out)
            return out
        missing = np.unique(rows[self._filled[rows] == 0])
        if len(missing) and not getattr(self._c.source, "random_access", True):
            self.preload()  # decoding a video up to a frame costs as much as decoding them all
        elif len(missing):
            self._fill(missing)
        return np.asarray(self._cache[rows])  # fancy indexing copies; asarray drops the memmap subclass

    def _check_all_images(self, P: _Problems, only_existing: bool = False, chunk: int = 64) -> None:
        """Decode every image and report unreadable ones and wrong sizes (for ``check_dataset``)."""
        source = self._c.source
        W, H = self.source_image_size
        if isinstance(source, PngImages):
            jobs = [(int(f), c) for f in self.frame_ids for c in range(len(self.cameras))]
            if only_existing:
                jobs = [(f, c) for f, c in jobs if (self.path / source.relpath(f, self.cameras[c])).is_file()]

            def check(job):
                f, c = job
                rel = source.relpath(f, self.cameras[c])
                if not (self.path / rel).is_file():
                    return None  # reported as missing already
                try:
                    image = decode_image(self.path / rel)
                except ValueError as exc:
                    return Problem(
                        "error", rel, "image", str(exc).split(": ", 1)[-1], frame=f, camera=self.cameras[c]
                    )
                if image.shape != (H, W, 3):
                    return Problem(
                        "error",
                        rel,
                        "size",
                        f"image is {image.shape[1]}x{image.shape[0]}, s3k.json image_size is {W}x{H}",
                        frame=f,
                        camera=self.cameras[c],
                    )
                return None

            with ThreadPoolExecutor(max_workers=self._workers) as pool:
                for problem in pool.map(check, jobs):
                    if problem is not None:
                        P.items.append(problem)
            return
        # Other sources: decode frame by frame, report the first failure of each chunk.
        for start in range(0, len(self), chunk):
            rows = np.arange(start, min(start + chunk, len(self)))
            buffer = np.empty((len(rows), len(self.cameras), H, W, 3), dtype=np.uint8)
            saved = self._resample
            self._resample = False
            try:
                self._decode_into(rows, buffer)
            except DatasetError as exc:
                P.items.extend(exc.problems)
            except ValueError as exc:
                P.error(str(exc).split(":")[0], "image", str(exc))
            finally:
                self._resample = saved

    # -- batches -----------------------------------------------------------------------------------------

    def batch(self, frame_ids) -> dict[str, Any]:
        """Everything about ``frame_ids`` for a training or evaluation step: ``frame_ids (B,)``,
        ``images uint8 (B, C, H, W, 3)``, ``cameras`` (``Cameras (B, C)``), ``uv (B, C, K, 2)``,
        ``label_mask (B, C, K)`` and, when the dataset has ground truth, ``points3d (B, K, 3)``,
        ``points3d_mask (B, K)``."""
        ids = np.asarray(frame_ids, dtype=np.int64)
        uv, mask = self.labels(ids)
        out = {
            "frame_ids": ids,
            "images": self.images(ids),
            "cameras": self.calibration(ids),
            "uv": uv,
            "label_mask": mask,
        }
        gt = self.points3d(ids)
        if gt is not None:
            out["points3d"], out["points3d_mask"] = gt
        return out

    def batches(
        self, split: str, batch_size: int, seed: int = 0, steps: int | None = None, drop_last: bool = True
    ) -> Iterator[dict[str, Any]]:
        """Random batches of a split (see :class:`RandomBatches`), each as :meth:`batch` returns."""
        for ids in RandomBatches(self.frames(split), batch_size, seed=seed, steps=steps, drop_last=drop_last):
            yield self.batch(ids)

    def summary(self) -> dict[str, Any]:
        """Counts for reports: frames per split, usable labels per split and per keypoint per camera in the
        labelled split, labelled frames with a keypoint seen by >= 2 cameras (triangulable), 3D points."""
        splits = {s: int((self._c.frames.splits == s).sum()) for s in SPLITS}
        in_split = {s: self._c.frames.splits == s for s in SPLITS}
        train = self._label_mask[in_split["labelled"]]
        per = {
            k: {c: int(train[:, ci, ki].sum()) for ci, c in enumerate(self.cameras)}
            for ki, k in enumerate(self.keypoints)
        }
        X = self._c.points3d
        return {
            "frames": len(self),
            "splits": splits,
            "labels": per,
            "labels_per_split": {s: int(self._label_mask[m].sum()) for s, m in in_split.items()},
            "triangulable_labelled_frames": int((train.sum(1) >= 2).any(-1).sum()),
            "points3d": None if X is None else int(np.isfinite(X).all(-1).sum()),
            "calibration": "static" if self.static_calibration else "per_frame",
            "image_size": self.source_image_size,
            "units": self.units,
        }


class RandomBatches:
    """Seeded random batches of frame ids: each epoch is a fresh permutation, cut into batches.

    Args:
        frame_ids: ``(N,)`` ids to draw from.
        batch_size: frames per batch; when larger than ``N`` with ``drop_last``, batches draw across epochs.
        seed: the stream is a function of ``seed`` only.
        steps: stop after this many batches (None: endless).
        drop_last: True gives only full batches (draws continue into the next permutation).

    Example:
        >>> [b.tolist() for b in RandomBatches([1, 2, 3], 2, seed=0, steps=3)]  # doctest: +SKIP
    """

    def __init__(
        self, frame_ids, batch_size: int, seed: int = 0, steps: int | None = None, drop_last: bool = True
    ):
        self.frame_ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        if len(self.frame_ids) == 0:
            raise ValueError("RandomBatches needs at least one frame id")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.batch_size, self.seed, self.steps, self.drop_last = int(batch_size), seed, steps, drop_last

    def __iter__(self) -> Iterator[np.ndarray]:
        rng = np.random.default_rng(self.seed)
        pending = np.empty(0, dtype=np.int64)
        made = 0
        while self.steps is None or made < self.steps:
            perm = self.frame_ids[rng.permutation(len(self.frame_ids))]
            if not self.drop_last:
                for start in range(0, len(perm), self.batch_size):
                    if self.steps is not None and made >= self.steps:
                        return
                    yield perm[start : start + self.batch_size]
                    made += 1
                continue
            pending = np.concatenate([pending, perm])
            while len(pending) >= self.batch_size and (self.steps is None or made < self.steps):
                yield pending[: self.batch_size]
                pending = pending[self.batch_size :]
                made += 1


# ----------------------------------------------------------------------------------------------------------
# Writing.


def _json_text(data: Any) -> str:
    """Indented JSON with each list of scalars on one line, so matrices read row by row."""
    text = json.dumps(data, indent=2)
    return re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def _fmt(x: float) -> str:
    """Shortest text that reads back to the same float64."""
    return repr(float(x))


class DatasetWriter:
    """Write a dataset folder frame by frame; tables and s3k.json are written by :meth:`close`.

    Args:
        path: folder to create (must be absent or empty unless ``overwrite``).
        keypoints: keypoint names (``K``).
        cameras: camera names (``C``), used as folder names.
        image_size: ``(W, H)`` of every image.
        units: world units of calibration and 3D points.
        calibration: a static rig (``Cameras (C,)``, ``(K, dist, R, t)`` or dict); then ``add_frame`` needs
            none. Without it every frame brings its own, written as a static rig when all are identical
            (unless ``per_frame_calibration=True``).
        per_frame_calibration: force per-frame (True) or static (False; frames must agree) calibration.
        skeleton, description, source: optional metadata (``source`` may be a string or a JSON object).
        videos: ``{camera: video file}`` to copy into ``videos/``; frames then carry no images and are
            ``video_frame`` (``extra``, default the frame id) of each video.
        png_compression: 0-9, OpenCV's PNG compression level.
        overwrite: replace an existing non-empty folder.

    Example:
        >>> with DatasetWriter("ds", ["a"], ["cam0", "cam1"], (64, 48)) as w:  # doctest: +SKIP
        ...     w.add_frame(0, "labelled", images, cams, labels)
    """

    def __init__(
        self,
        path: str | Path,
        keypoints: Sequence[str],
        cameras: Sequence[str],
        image_size: Sequence[int],
        units: str = "m",
        *,
        calibration: Any = None,
        per_frame_calibration: bool | None = None,
        skeleton: Sequence[Sequence[str]] | None = None,
        description: str | None = None,
        source: Any = None,
        videos: dict[str, str | Path] | None = None,
        png_compression: int = 3,
        overwrite: bool = False,
    ):
        self.path = Path(path)
        self.keypoints, self.cameras = list(keypoints), list(cameras)
        P = _Problems()
        meta = {"keypoints": self.keypoints, "cameras": self.cameras}
        _names(meta, "keypoints", P, folder_safe=False)
        _names(meta, "cameras", P, folder_safe=True)
        if P.errors:
            raise ValueError("; ".join(f"{p.field}: {p.message}" for p in P.errors))
        if len(image_size) != 2 or any(int(s) != s or s <= 0 for s in image_size):
            raise ValueError(f"image_size must be (W, H) positive integers, got {image_size!r}")
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.units = units
        for a, b in skeleton or []:
            for n in (a, b):
                if n not in self.keypoints:
                    raise ValueError(f"skeleton: unknown keypoint {n!r}; keypoints are {self.keypoints}")
        self.skeleton = [list(e) for e in skeleton or []]
        self.description, self.source = description, source
        self.png_params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
        self.static = None if calibration is None else self._check_calibration(calibration, "calibration")
        if self.static is not None and per_frame_calibration:
            raise ValueError("per_frame_calibration=True contradicts a static calibration argument")
        self.per_frame_calibration = per_frame_calibration
        if self.path.exists() and any(self.path.iterdir()):
            if not overwrite:
                raise FileExistsError(f"{self.path}: folder exists and is not empty (pass overwrite=True)")
            shutil.rmtree(self.path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.videos = None
        if videos is not None:
            missing = sorted(set(self.cameras) - set(videos))
            if missing:
                raise ValueError(f"videos: no video for cameras {missing}")
            (self.path / "videos").mkdir()
            self.videos = {}
            for cam in self.cameras:
                src = Path(videos[cam])
                rel = f"videos/{cam}{src.suffix}"
                shutil.copyfile(src, self.path / rel)
                self.videos[cam] = rel
        else:
            for cam in self.cameras:
                (self.path / "images" / cam).mkdir(parents=True, exist_ok=True)
        self._frames: list[tuple[int, str, dict]] = []
        self._seen: set[int] = set()
        self._calibrations: list[CameraArrays] = []
        self._labels: list[str] = []
        self._points: list[str] = []
        self._closed = False

    def _check_calibration(self, calibration: Any, arg: str) -> CameraArrays:
        cal = camera_arrays(calibration)
        C = len(self.cameras)
        for name, value, shape in zip(("K", "dist", "R", "t"), cal, ((C, 3, 3), (C, 5), (C, 3, 3), (C, 3))):
            if value.shape != shape:
                raise ValueError(f"{arg}.{name} must have shape {shape}, got {value.shape}")
        for c, found in enumerate(_camera_defects(*cal)):
            for fld, message in found:
                raise ValueError(f"{arg}.{fld} of camera {self.cameras[c]!r}: {message}")
        return cal

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    def add_frame(
        self,
        frame_id: int,
        split: str,
        images: Any = None,
        calibration: Any = None,
        labels: Any = None,
        points3d: Any = None,
        visible: Any = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """Add one frame.

        Args:
            frame_id: non-negative integer, unique.
            split: ``"labelled" | "unlabelled" | "test"``.
            images: ``uint8 (C, H, W, 3)`` RGB (or a sequence / ``{camera: image}``); None for video datasets.
            calibration: this frame's ``Cameras (C,)`` or ``(K, dist, R, t)``; None with a static rig.
            labels: ``uv (C, K, 2)`` pixels, NaN where not labelled; or ``(uv, mask (C, K))``; or None.
            points3d: ground truth ``(K, 3)`` (NaN rows are skipped), or None.
            visible: ``(C, K)`` bool; False writes a labelled-but-occluded row (``visible = 0``, masked).
            extra: more frames.csv columns for this frame, e.g. ``{"instance": 3, "segment": 0}``.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        if isinstance(frame_id, bool) or int(frame_id) != frame_id or frame_id < 0:
            raise ValueError(f"frame_id must be a non-negative integer, got {frame_id!r}")
        frame_id = int(frame_id)
        if frame_id in self._seen:
            raise ValueError(f"frame_id {frame_id} added twice")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {list(SPLITS)}, got {split!r}")
        C, Kp = len(self.cameras), len(self.keypoints)
        W, H = self.image_size
        extra = dict(extra or {})
        for key in extra:
            if key in FRAMES_COLUMNS or not _NAME_RE.match(str(key)) or "," in str(key):
                raise ValueError(f"extra column name {key!r} is reserved or not a plain name")

        if calibration is None:
            if self.static is None:
                raise ValueError("calibration is required (the writer has no static calibration)")
            cal = self.static
        else:
            cal = self._check_calibration(calibration, "calibration")
            if self.static is not None and not all(np.array_equal(a, b) for a, b in zip(cal, self.static)):
                raise ValueError("calibration differs from the writer's static calibration")

        if self.videos is None:
            if images is None:
                raise ValueError("images are required (C, H, W, 3) uint8")
            if isinstance(images, dict):
                images = [images[c] for c in self.cameras]
            imgs = [np.asarray(im) for im in images]
            if len(imgs) != C:
                raise ValueError(f"images: expected {C} cameras, got {len(imgs)}")
            for c, im in enumerate(imgs):
                if im.shape != (H, W, 3) or im.dtype != np.uint8:
                    raise ValueError(
                        f"images[{c}] ({self.cameras[c]}) must be uint8 {(H, W, 3)}, got "
                        f"{im.dtype} {im.shape}"
                    )
        elif images is not None:
            raise ValueError("this writer stores videos; pass images=None and extra={'video_frame': i}")

        label_rows = []
        if labels is not None:
            if isinstance(labels, tuple):
                uv, lmask = (np.asarray(x) for x in labels)
            else:
                uv = np.asarray(labels, dtype=np.float64)
                lmask = np.isfinite(uv).all(-1)
            uv = np.asarray(uv, dtype=np.float64)
            if uv.shape != (C, Kp, 2) or lmask.shape != (C, Kp):
                raise ValueError(f"labels must be uv {(C, Kp, 2)} (and mask {(C, Kp)}), got {uv.shape}")
            vis = np.ones((C, Kp), bool) if visible is None else np.asarray(visible, bool)
            if vis.shape != (C, Kp):
                raise ValueError(f"visible must have shape {(C, Kp)}, got {vis.shape}")
            for c, k in zip(*np.nonzero(lmask.astype(bool))):
                u, v = uv[c, k]
                if vis[c, k] and not (np.isfinite(u) and np.isfinite(v)):
                    raise ValueError(f"labels[{c}, {k}] is marked labelled but not finite: {uv[c, k]}")
                cells = ["" if not np.isfinite(x) else _fmt(x) for x in (u, v)]
                label_rows.append(
                    f"{frame_id},{self.cameras[c]},{self.keypoints[k]},{cells[0]},{cells[1]},{int(vis[c, k])}"
                )
        point_rows = []
        if points3d is not None:
            X = np.asarray(points3d, dtype=np.float64)
            if X.shape != (Kp, 3):
                raise ValueError(f"points3d must have shape {(Kp, 3)}, got {X.shape}")
            for k in range(Kp):
                if np.isfinite(X[k]).all():
                    point_rows.append(f"{frame_id},{self.keypoints[k]},{','.join(_fmt(x) for x in X[k])}")

        if self.videos is None:
            for c, im in enumerate(imgs):
                rel = DEFAULT_IMAGE_PATTERN.format(camera=self.cameras[c], frame=frame_id)
                ok, data = cv2.imencode(".png", cv2.cvtColor(im, cv2.COLOR_RGB2BGR), self.png_params)
                if not ok:  # pragma: no cover
                    raise ValueError(f"{rel}: PNG encoding failed")
                data.tofile(str(self.path / rel))
        self._seen.add(frame_id)
        self._frames.append((frame_id, split, extra))
        self._calibrations.append(cal)
        self._labels.extend(label_rows)
        self._points.extend(point_rows)

    def close(self) -> Path:
        """Write frames.csv, calibration, labels.csv, points3d.csv and (last) s3k.json; returns the folder."""
        if self._closed:
            return self.path
        if not self._frames:
            raise ValueError(f"{self.path}: no frames added")
        static = self.static
        if static is None:
            first = self._calibrations[0]
            same = all(all(np.array_equal(a, b) for a, b in zip(first, cal)) for cal in self._calibrations)
            if self.per_frame_calibration is False and not same:
                raise ValueError("per_frame_calibration=False but frames have different calibrations")
            if same and not self.per_frame_calibration:
                static = first
        columns: list[str] = []
        for _, _, extra in self._frames:
            columns.extend(k for k in extra if k not in columns)
        with open(self.path / FRAMES_FILE, "w", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow([*FRAMES_COLUMNS, *columns])
            for frame, split, extra in self._frames:
                writer.writerow([frame, split, *(extra.get(k, "") for k in columns)])
        if static is not None:
            cams = {
                cam: {
                    "K": static.K[c].tolist(),
                    "dist": static.dist[c].tolist(),
                    "R": static.R[c].tolist(),
                    "t": static.t[c].tolist(),
                }
                for c, cam in enumerate(self.cameras)
            }
            (self.path / STATIC_CALIBRATION_FILE).write_text(_json_text({"cameras": cams}))
        else:
            with open(self.path / PER_FRAME_CALIBRATION_FILE, "w") as f:
                f.write(",".join(CALIBRATION_COLUMNS) + "\n")
                for (frame, _, _), cal in zip(self._frames, self._calibrations):
                    for c, cam in enumerate(self.cameras):
                        nums = [*cal.K[c].ravel(), *cal.dist[c], *cal.R[c].ravel(), *cal.t[c]]
                        f.write(f"{frame},{cam}," + ",".join(_fmt(x) for x in nums) + "\n")
        if self._labels:
            (self.path / LABELS_FILE).write_text(
                ",".join(LABELS_COLUMNS) + "\n" + "\n".join(self._labels) + "\n"
            )
        if self._points:
            (self.path / POINTS3D_FILE).write_text(
                ",".join(POINTS3D_COLUMNS) + "\n" + "\n".join(self._points) + "\n"
            )
        meta: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "keypoints": self.keypoints,
            "cameras": self.cameras,
            "image_size": list(self.image_size),
            "units": self.units,
            "calibration": "static" if static is not None else "per_frame",
            "images": (
                {"type": "png", "pattern": DEFAULT_IMAGE_PATTERN}
                if self.videos is None
                else {"type": "video", "videos": self.videos}
            ),
        }
        if self.skeleton:
            meta["skeleton"] = self.skeleton
        if self.description is not None:
            meta["description"] = self.description
        if self.source is not None:
            meta["source"] = self.source
        (self.path / METADATA_FILE).write_text(_json_text(meta))
        self._closed = True
        return self.path


def open_dataset(path: str | Path, **kwargs: Any) -> Dataset:
    """Shorthand for :meth:`Dataset.open`."""
    return Dataset.open(path, **kwargs)
