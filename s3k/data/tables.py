"""The dataset's tables: ``s3k.json``, ``frames.csv``, ``labels.csv`` and ``points3d.csv`` (the calibration
tables are read by :mod:`s3k.data.cameras`).

Each reader parses one file into numpy arrays and reports every problem it finds to a
:class:`~s3k.data.problems.Problems`, naming the file, the field and the line/frame/camera/keypoint. The
layout of the folder is described in ``docs/dataset-format.md``.
"""

from __future__ import annotations

import csv
import io
import json
import re
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from s3k.data.problems import Problems

FORMAT_NAME = "s3k-dataset"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
SPLITS = ("labelled", "unlabelled", "test")
CALIBRATION_MODES = ("static", "per_frame", "per_session")

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

# Camera names are folder names; keypoint names are CSV cells (written unquoted) and must survive a strip().
NAME_RE = re.compile(r"^[A-Za-z0-9_+-][A-Za-z0-9_.+-]*$")
_BAD_CELL_RE = re.compile(r"[,\"\r\n]|^\s|\s$")


# ----------------------------------------------------------------------------------------------------------
# Metadata and tables.


def read_csv(root: Path, name: str, required: Sequence[str], P: Problems) -> tuple[list[str], list] | None:
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


def read_json(root: Path, name: str, missing: str, P: Problems) -> tuple[bool, Any]:
    """``(True, content)`` of the JSON file ``root / name``, or ``(False, None)`` after reporting why it
    cannot be read (``missing`` is the message for an absent file)."""
    try:
        return True, json.loads((root / name).read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        P.error(name, None, missing)
    except json.JSONDecodeError as exc:
        P.error(name, None, f"not valid JSON: {exc.msg}", line=exc.lineno)
    except (OSError, UnicodeDecodeError) as exc:
        P.error(name, None, f"cannot read: {exc}")
    return False, None


def check_names(meta: dict, key: str, P: Problems, folder_safe: bool) -> list[str] | None:
    """The names ``meta[key]`` (keypoints or cameras), or None after reporting why they cannot be used:
    empty, repeated, holding CSV-breaking characters or, with ``folder_safe``, unusable as folder names."""
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
        bad = [v for v in value if not NAME_RE.match(v)]
        if bad:
            P.error(
                METADATA_FILE, key, f"names {bad} must be usable as folder names (letters, digits, _ . + -)"
            )
            return None
    return list(value)



@dataclass
class Meta:
    raw: dict
    keypoints: list[str]
    cameras: list[str]
    image_size: tuple[int, int]
    units: str
    calibration: str
    images: dict
    skeleton: list[tuple[str, str]]


def _check_image_pattern(pattern: Any, P: Problems) -> None:
    """Record an error unless ``images.pattern`` is a relative path inside the folder that uses both
    ``{camera}`` and ``{frame}``."""
    try:
        ok = isinstance(pattern, str) and pattern.format(camera="a", frame=1) != pattern.format(
            camera="b", frame=2
        )
        ok = ok and pattern.format(camera="a", frame=1) != pattern.format(camera="a", frame=2)
        ok = ok and pattern.format(camera="a", frame=1) != pattern.format(camera="b", frame=1)
        where = PurePosixPath(pattern.format(camera="a", frame=1).replace("\\", "/"))
        ok = ok and not where.is_absolute() and ".." not in where.parts and ":" not in where.parts[0]
    except (KeyError, IndexError, ValueError, AttributeError):
        ok = False
    if not ok:
        P.error(
            METADATA_FILE,
            "images.pattern",
            "must be a relative path inside the dataset folder that uses both {camera} and {frame} "
            f"(e.g. {DEFAULT_IMAGE_PATTERN!r}), got {pattern!r}",
        )


def read_metadata(root: Path, P: Problems, image_types: Collection[str]) -> Meta | None:
    """``s3k.json``; ``image_types`` are the known ``images.type`` values (:mod:`s3k.data.sources`)."""
    if not root.is_dir():
        P.error(str(root), None, "not a folder")
        return None
    ok, meta = read_json(root, METADATA_FILE, "file missing: every dataset folder starts with s3k.json", P)
    if not ok:
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
    keypoints = check_names(meta, "keypoints", P, folder_safe=False)
    cameras = check_names(meta, "cameras", P, folder_safe=True)
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
    if not isinstance(images, dict) or images.get("type", "png") not in image_types:
        P.error(
            METADATA_FILE,
            "images",
            f"must be an object whose 'type' is one of {sorted(image_types)}, got {images!r}",
        )
    elif images.get("type", "png") == "png":
        _check_image_pattern(images.get("pattern", DEFAULT_IMAGE_PATTERN), P)
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
            if a == b:
                P.error(METADATA_FILE, "skeleton", f"edge [{a!r}, {b!r}] joins a keypoint to itself")
            skeleton.append((a, b))
    if len(P.errors) > n_errors:
        return None
    assert keypoints is not None and cameras is not None and size is not None  # else errors were recorded
    return Meta(meta, keypoints, cameras, (size[0], size[1]), units, mode, dict(images), skeleton)



def parse_int(text: str) -> int | None:
    """The integer ``text`` holds when it fits in 64 bits (frame ids are stored as int64), else None."""
    try:
        value = int(text)
    except ValueError:
        return None
    return value if -(2**63) <= value < 2**63 else None


def parse_float(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


@dataclass
class Frames:
    ids: np.ndarray  # (N,) int64, file order
    splits: np.ndarray  # (N,) str
    columns: dict[str, np.ndarray]  # extra columns, as text
    lines: np.ndarray  # (N,) line numbers in frames.csv
    row_of: dict[int, int]


def read_frames(root: Path, P: Problems) -> Frames | None:
    table = read_csv(root, FRAMES_FILE, FRAMES_COLUMNS, P)
    if table is None:
        return None
    header, rows = table
    ids: list[int] = []
    splits: list[str] = []
    lines: list[int] = []
    extra: dict[str, list[str]] = {c: [] for c in header if c not in FRAMES_COLUMNS}
    seen: dict[int, int] = {}
    for line, row in rows:
        frame = parse_int(row["frame"])
        if frame is None or frame < 0:
            P.error(FRAMES_FILE, "frame", f"must be a non-negative integer below 2^63, got {row['frame']!r}",
                    line=line)
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
            value = parse_int(text)
            if value is None or value < 0:
                P.error(
                    FRAMES_FILE,
                    "video_frame",
                    f"must be a non-negative integer, got {text!r}",
                    line=line,
                    frame=frame,
                )
    return Frames(
        np.asarray(ids, dtype=np.int64),
        np.asarray(splits, dtype=object),
        {c: np.asarray(v, dtype=object) for c, v in extra.items()},
        np.asarray(lines, dtype=np.int64),
        {f: i for i, f in enumerate(ids)},
    )


def locate(
    name: str, line: int, row: dict, frames: Frames, P: Problems, **known: list[str]
) -> tuple[int, int, list[int]] | None:
    """Where a table row belongs: ``(frame id, its row in frames.csv, [position of row[column] among the
    s3k.json names for each column=names in known])``, or None after reporting a frame that frames.csv does
    not list or an unknown camera/keypoint name (every unknown name is reported)."""
    frame = parse_int(row["frame"])
    if frame is None or frame not in frames.row_of:
        P.error(name, "frame", f"frame {row['frame']!r} is not listed in {FRAMES_FILE}", line=line)
        return None
    found = []
    for column, names in known.items():
        value = row[column]
        if value in names:
            found.append(names.index(value))
        else:
            P.error(name, column, f"unknown {column} {value!r}; s3k.json {column}s are {names}", line=line,
                    frame=frame)
    if len(found) < len(known):
        return None
    return frame, frames.row_of[frame], found

@dataclass
class Labels:
    uv: np.ndarray  # (N, C, K, 2) float64, NaN where absent
    present: np.ndarray  # (N, C, K) a row exists
    visible: np.ndarray  # (N, C, K) visible == 1
    inside: np.ndarray  # (N, C, K) (u, v) within the image


def read_labels(root: Path, meta: Meta, frames: Frames, P: Problems) -> Labels:
    N, C, Kp = len(frames.ids), len(meta.cameras), len(meta.keypoints)
    labels = Labels(
        np.full((N, C, Kp, 2), np.nan),
        np.zeros((N, C, Kp), bool),
        np.zeros((N, C, Kp), bool),
        np.zeros((N, C, Kp), bool),
    )
    name = LABELS_FILE
    if not (root / name).exists():
        return labels
    table = read_csv(root, name, LABELS_COLUMNS[:5], P)
    if table is None:
        return labels
    _, rows = table
    W, H = meta.image_size
    first_line: dict[tuple[int, int, int], int] = {}
    for line, row in rows:
        found = locate(name, line, row, frames, P, camera=meta.cameras, keypoint=meta.keypoints)
        if found is None:
            continue
        frame, i, (c, k) = found
        where: dict[str, Any] = {"line": line, "frame": frame}
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
            value = parse_float(text) if text else (np.nan if not visible else None)
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


def read_points3d(root: Path, meta: Meta, frames: Frames, P: Problems) -> np.ndarray | None:
    name = POINTS3D_FILE
    if not (root / name).exists():
        return None
    table = read_csv(root, name, POINTS3D_COLUMNS, P)
    if table is None:
        return None
    _, rows = table
    X = np.full((len(frames.ids), len(meta.keypoints), 3), np.nan)
    first_line: dict[tuple[int, int], int] = {}
    for line, row in rows:
        found = locate(name, line, row, frames, P, keypoint=meta.keypoints)
        if found is None:
            continue
        frame, i, (k,) = found
        where = {"line": line, "frame": frame, "keypoint": row["keypoint"]}
        xyz = [parse_float(row[c]) for c in "xyz"]
        bad = [c for c, value in zip("xyz", xyz) if value is None or not np.isfinite(value)]
        if bad:
            P.error(name, bad[0], f"must be a finite number, got {row[bad[0]]!r}", **where)
            continue
        if (i, k) in first_line:
            P.error(name, None, f"point given twice (first on line {first_line[(i, k)]})", **where)
            continue
        first_line[(i, k)] = line
        X[i, k] = xyz
    return X

