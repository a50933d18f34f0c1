"""DeepLabCut / Lightning Pose label CSVs: :func:`read_dlc_csv` and Lightning Pose's multi-view layout
(:func:`find_lightning_pose_csvs`, one ``CollectedData_<view>.csv`` per view)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path, open_text
from s3k.data.formats.labels2d import LabelTable, frame_id_from_path
from s3k.data.formats.skeleton import dlc_project_config, read_skeleton


def _bodypart_columns(path: Path, coords_row: list[str], parts_row: list[str], n_index: int
                      ) -> tuple[list[str], dict[str, int], dict[str, int]]:
    """The bodyparts in column order and the columns of their x and y."""
    keypoints: list[str] = []
    x_col: dict[str, int] = {}
    y_col: dict[str, int] = {}
    for col in range(n_index, len(coords_row)):
        coord = coords_row[col].strip().lower()
        part = parts_row[col].strip() if col < len(parts_row) else ""
        if not part:
            raise UserError(f"{path}: header row 'bodyparts' is empty at column {col + 1}")
        if coord not in ("x", "y", "likelihood"):
            raise UserError(
                f"{path}: header row 'coords' column {col + 1} is {coords_row[col]!r}; "
                "expected x, y or likelihood"
            )
        if part not in keypoints:
            keypoints.append(part)
        target = x_col if coord == "x" else y_col if coord == "y" else None
        if target is not None:
            if part in target:
                raise UserError(f"{path}: bodypart {part!r} has two {coord!r} columns")
            target[part] = col
    for part in keypoints:
        if part not in x_col or part not in y_col:
            raise UserError(f"{path}: bodypart {part!r} needs both an x and a y column")
    if not keypoints:
        raise UserError(f"{path}: no bodypart columns")
    return keypoints, x_col, y_col


def _row_points(path: Path, row: list[str], line: int, index_text: str, keypoints: list[str],
                x_col: dict[str, int], y_col: dict[str, int]) -> np.ndarray:
    """``(K, 2)`` the row's points, NaN where a cell is empty."""
    uv = np.full((len(keypoints), 2), np.nan)
    for k, part in enumerate(keypoints):
        for a, col in enumerate((x_col[part], y_col[part])):
            cell = row[col].strip()
            if cell == "" or cell.lower() == "nan":
                continue
            try:
                uv[k, a] = float(cell)
            except ValueError:
                raise UserError(
                    f"{path}: line {line} ({index_text or 'no image path'}), bodypart {part!r} "
                    f"{'xy'[a]}: {cell!r} is not a number"
                ) from None
    return uv


def _header_rows(path: Path, rows: list[list[str]]) -> tuple[dict[str, list[str]], int, int]:
    """A label CSV's header rows by name, the first data row, and the number of leading index columns (those
    whose ``coords`` cell is empty); refuses missing header rows and a multi-animal CSV."""
    header: dict[str, list[str]] = {}
    r = 0
    while r < len(rows) and rows[r] and rows[r][0].strip().lower() in ("scorer", "individuals", "bodyparts",
                                                                       "coords"):
        header[rows[r][0].strip().lower()] = rows[r]
        r += 1
    for name in ("scorer", "bodyparts", "coords"):
        if name not in header:
            raise UserError(
                f"{path}: missing the {name!r} header row (expected three header rows "
                "scorer/bodyparts/coords, each starting with its name)"
            )
    coords_row = header["coords"]
    n_index = 1
    while n_index < len(coords_row) and coords_row[n_index].strip() == "":
        n_index += 1
    if "individuals" in header:
        individuals = {v.strip() for v in header["individuals"][n_index:] if v.strip()}
        if len(individuals) > 1:
            raise UserError(
                f"{path}: multi-animal CSV with individuals {sorted(individuals)}; s3k imports one animal "
                "per recording (split the CSV per individual)"
            )
    return header, r, n_index


def read_dlc_csv(path: str | Path, frame_ids_from: str = "path") -> LabelTable:
    """Read a DeepLabCut / Lightning Pose label CSV.

    Layout: header rows ``scorer``, (``individuals``, single animal only), ``bodyparts``, ``coords``; then one
    row per image: leading index column(s) with the image path (or a frame number), then ``x, y`` (and
    optionally ``likelihood``, ignored) per bodypart. Empty cells (or NaN) mean unlabelled. A CSV in
    DeepLabCut's project layout (``PROJECT/labeled-data/VIDEO/``) takes the skeleton of
    ``PROJECT/config.yaml`` (its edges between the CSV's bodyparts).

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
    with open_text(path) as f:
        rows = list(csv.reader(f))
    header, r, n_index = _header_rows(path, rows)
    coords_row, parts_row = header["coords"], header["bodyparts"]
    keypoints, x_col, y_col = _bodypart_columns(path, coords_row, parts_row, n_index)
    ids: list[int] = []
    uvs: list[np.ndarray] = []
    n_cols = len(coords_row)
    for row_no, row in enumerate(rows[r:]):
        line = r + row_no + 1  # 1-based line number for messages
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) > n_cols:
            raise UserError(f"{path}: line {line} has {len(row)} cells, the header has {n_cols}")
        row = row + [""] * (n_cols - len(row))
        index_text = "/".join(cell.strip() for cell in row[:n_index] if cell.strip())
        frame = None
        if frame_ids_from == "path":
            frame = frame_id_from_path(index_text) if not index_text.isdigit() else int(index_text)
        if frame is None:
            frame = row_no
        uv = _row_points(path, row, line, index_text, keypoints, x_col, y_col)
        # A keypoint is labelled only when both coordinates are.
        uv[np.isnan(uv).any(axis=1)] = np.nan
        ids.append(frame)
        uvs.append(uv)
    if not ids:
        raise UserError(f"{path}: no label rows after the header")
    frame_ids = np.asarray(ids, dtype=np.int64)
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
        raise UserError(
            f"{path}: frame ids {dup} appear on several rows (frame ids come from the image names; use "
            "frame_ids_from='row' if the names do not number the frames)"
        )
    order = np.argsort(frame_ids)
    table = LabelTable(keypoints, frame_ids[order], np.stack(uvs)[order], str(path))
    config = dlc_project_config(path)
    if config is not None:  # the project's skeleton, where the CSV lies in DeepLabCut's project layout
        table.skeleton = [e for e in read_skeleton(config) if set(e) <= set(keypoints)]
        table.skeleton_source = str(config)
    return table


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



def write_dlc_csv(path: str | Path, table: LabelTable, image_paths: list[str], scorer: str = "s3k") -> Path:
    """Write labels as a DeepLabCut / Lightning Pose label CSV (header rows scorer/bodyparts/coords, then
    one row per image: its path, then ``x, y`` per bodypart, empty where unlabelled).

    Args:
        path: the CSV (written beside, then renamed).
        table: the labels; one row per entry of ``table.frame_ids``.
        image_paths: the image path of each row, relative to the project folder (``labeled-data/...``).
        scorer: the scorer (annotator) name of the header.
    """
    if len(image_paths) != len(table.frame_ids):
        raise ValueError(f"{len(image_paths)} image paths for {len(table.frame_ids)} frames")
    header = [
        ["scorer"] + [scorer] * (2 * len(table.keypoints)),
        ["bodyparts"] + [k for k in table.keypoints for _ in (0, 1)],
        ["coords"] + ["x", "y"] * len(table.keypoints),
    ]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerows(header)
        for image, uv in zip(image_paths, table.uv):
            # repr: the shortest text that reads back to the same float64
            writer.writerow([image] + ["" if not np.isfinite(x) else repr(float(x)) for x in uv.ravel()])
    return path
