"""The 3D keypoints CSV of ``s3k predict`` and ``s3k track``: anipose's 3D layout, its writer and its reader.

Columns, one row per frame::

    <kp>_x, <kp>_y, <kp>_z, <kp>_error, <kp>_ncams, <kp>_score   for every keypoint, then fnum

``x, y, z`` are in the world units of the calibration; ``error`` is the mean reprojection error, in pixels of
the cameras' images, over the cameras used; ``ncams`` the number of cameras used; ``score`` the mean
confidence weight over all cameras; ``fnum`` the frame number (video frame index, or dataset frame id).
Where the triangulation is degenerate ``x, y, z`` and ``error`` are ``nan`` (:mod:`s3k.readout`).

The CSV has no room for its unit (anipose's readers take every column as data), so ``s3k track`` and ``s3k
predict`` write it beside the CSV, in ``<file>.s3k.json`` (:func:`write_source`): the world unit of the
points, the run and the calibration or dataset they came from. ``s3k export-tracks`` reads the unit from it
(:func:`read_source`) rather than guessing one.
"""

from __future__ import annotations

import contextlib
import csv
import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base import outputs
from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path, atomic_write_json, open_text

__all__ = ["array_rows", "check_output", "csv_header", "csv_rows", "read_csv", "read_source", "rows_points",
           "source_path", "write_csv", "write_source"]


def csv_header(keypoints: Sequence[str]) -> list[str]:
    """anipose's 3D CSV columns: ``<kp>_x, _y, _z, _error, _ncams, _score`` per keypoint, then ``fnum``."""
    cols = []
    for kp in keypoints:
        cols += [f"{kp}_x", f"{kp}_y", f"{kp}_z", f"{kp}_error", f"{kp}_ncams", f"{kp}_score"]
    return cols + ["fnum"]


def _fmt(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.8g}"


def csv_rows(fnums: Sequence[int], result: Any) -> list[list[str]]:
    """One CSV row per frame of ``result``, a :class:`s3k.readout.ReadOut` (its ``X``, ``error``, ``ncams``
    and ``score``; columns of :func:`csv_header`)."""
    return array_rows(fnums, result.X.cpu().numpy(), result.error.cpu().numpy(), result.ncams.cpu().numpy(),
                      result.score.cpu().numpy())


def array_rows(fnums: Sequence[int], X: np.ndarray, error: np.ndarray, ncams: np.ndarray,
               score: np.ndarray) -> list[list[str]]:
    """One CSV row per frame from arrays: ``X (B, K, 3)``, ``error``, ``ncams``, ``score`` ``(B, K)``."""
    rows = []
    for b, fnum in enumerate(fnums):
        row: list[str] = []
        for k in range(X.shape[1]):
            row += [_fmt(v) for v in X[b, k]]
            row += [_fmt(error[b, k]), str(int(ncams[b, k])), f"{score[b, k]:.6f}"]
        rows.append(row + [str(int(fnum))])
    return rows


def rows_points(rows: Sequence[Sequence[str]], num_keypoints: int) -> dict[int, np.ndarray]:
    """The 3D points of :func:`csv_rows`' rows as the file holds them, ``{fnum: (K, 3)}`` (NaN where not
    triangulated): what :func:`read_csv` reads back from those rows, without the file."""
    per = len(csv_header(["k"])) - 1  # the columns of one keypoint
    return {int(row[-1]): np.array([[float(v) for v in row[per * k:per * k + 3]]
                                    for k in range(num_keypoints)]) for row in rows}


def check_output(path: str | Path, overwrite: bool, dataset: str | Path | None = None) -> Path:
    """Refuse an output file inside a dataset (``dataset`` or any other), a run's own file, a folder, or an
    existing file without overwrite (:func:`s3k.base.outputs.check_output`).

    Raises:
        UserError: naming the file (and ``--overwrite`` where it helps).
    """
    return outputs.check_output(path, overwrite, inputs={"--data": dataset})


@contextlib.contextmanager
def write_csv(path: str | Path, keypoints: Sequence[str]) -> Iterator[csv.Writer]:  # type: ignore[name-defined]
    """Open the CSV for writing (header written); the file appears complete, or not at all, on exit."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(csv_header(keypoints))
        yield writer


def read_csv(path: str | Path, keypoints: Sequence[str]) -> dict[int, np.ndarray]:
    """The 3D points of a CSV written by :func:`write_csv`: ``{fnum: (K, 3)}``.

    Args:
        path: the CSV file.
        keypoints: names of the keypoints to read, in the order wanted.

    Returns:
        One ``(K, 3)`` float array per frame number, NaN where a keypoint was not triangulated.

    Raises:
        UserError: a keypoint's ``_x/_y/_z`` column or ``fnum`` is missing, or a value is not a number;
            the message names the file, the column and the line.
    """
    out: dict[int, np.ndarray] = {}
    with open_text(path) as f:
        reader = csv.DictReader(f)
        wanted = [f"{k}_{a}" for k in keypoints for a in "xyz"] + ["fnum"]
        missing = [c for c in wanted if c not in (reader.fieldnames or [])]
        if missing:
            raise UserError(f"{path}: missing column(s) {missing}; has {reader.fieldnames}")
        for row in reader:
            try:
                xyz = np.array([[float(row[f"{k}_{a}"] or "nan") for a in "xyz"] for k in keypoints])
                out[int(row["fnum"])] = xyz
            except ValueError as e:
                raise UserError(f"{path}, line {reader.line_num}: {e}") from None
            except TypeError:  # a short row: DictReader fills the missing cells with None
                raise UserError(f"{path}, line {reader.line_num}: the row has fewer cells than the header "
                                "(a truncated file?)") from None
    return out


def source_path(csv_path: str | Path) -> Path:
    """Where the source of a 3D CSV is written: ``<file>.s3k.json`` beside it."""
    csv_path = Path(csv_path)
    return csv_path.with_name(csv_path.name + ".s3k.json")


def write_source(csv_path: str | Path, units: str, details: dict[str, Any] | None = None,
                 **source: object) -> Path:
    """Write the unit of the CSV's points and where they came from (``run``, ``calibration``, ``dataset``...)
    beside it, and ``details`` as they are (JSON: the videos, the filter's settings); returns the file."""
    path = source_path(csv_path)
    atomic_write_json({"units": str(units), **{k: str(v) for k, v in source.items() if v is not None},
                       **(details or {})}, path)
    return path


#: The types of the entries of a CSV's source record (:func:`write_source`); others are kept as they are.
_SOURCE_TYPES: dict[str, tuple[type, ...]] = {
    "units": (str,), "run": (str,), "calibration": (str,), "dataset": (str,), "fps": (str, int, float),
    "videos": (dict,), "start": (int,), "raw": (str, type(None)), "doubt": (str, type(None)),
    "filter": (dict, type(None)), "frame_offsets": (dict,),
}


def read_source(csv_path: str | Path) -> dict[str, Any] | None:
    """What :func:`write_source` wrote beside a CSV, or None when there is no such file.

    Raises:
        UserError: the file is there but broken (not JSON, not an object, an entry of another type, a
            ``videos`` entry that is not ``{camera: file}``, a ``raw`` or ``doubt`` file outside the CSV's
            folder), naming the file and the entry.
    """
    path = source_path(csv_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot be read ({exc})") from None
    hint = f"delete {path.name} (then give what it recorded as options), or track the videos again"
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise UserError(f"{path}: broken, not JSON ({exc})", hint=hint) from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: broken, a JSON {type(doc).__name__} where an object was expected",
                        hint=hint)
    for key, types in _SOURCE_TYPES.items():
        if (key == "units" or key in doc) and (not isinstance(doc.get(key), types)
                                               or isinstance(doc.get(key), bool)):
            wanted = " or ".join("null" if t is type(None) else t.__name__ for t in types)
            raise UserError(f"{path}: broken, {key!r} is {doc.get(key)!r}, expected {wanted}", hint=hint)
    videos = doc.get("videos", {})
    if not all(isinstance(c, str) and isinstance(v, str) and c and v for c, v in videos.items()):
        raise UserError(f"{path}: broken, 'videos' is {videos!r}, expected {{camera: file}}", hint=hint)
    for key in ("raw", "doubt"):
        name = doc.get(key)
        if name is not None and (name in ("", ".", "..") or Path(name).name != name or "\\" in name):
            raise UserError(f"{path}: broken, {key!r} is {name!r}, expected the name of a file beside "
                            f"{Path(csv_path).name}", hint=hint)
    return doc


def tracked_with(csv_path: str | Path, run: str | Path) -> bool:
    """Whether ``csv_path`` is a track of ``run``'s present weights: its record (:func:`write_source`) names
    the same run folder and it is newer than every file of the run (a run trained on or fine-tuned again since
    is not)."""
    csv_path, run = Path(csv_path), Path(run)
    try:
        source = read_source(csv_path)
    except UserError:
        return False
    if source is None or not isinstance(source.get("run"), str) or not (csv_path.is_file() and run.is_dir()):
        return False
    newest = max((f.stat().st_mtime for f in run.rglob("*") if f.is_file()), default=float("inf"))
    return Path(source["run"]).resolve() == run.resolve() and csv_path.stat().st_mtime > newest
