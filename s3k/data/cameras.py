"""The dataset's calibration tables: ``calibration.json`` (a static rig) or ``calibration.csv`` (per frame).

Both give the rig as one :class:`s3k.geometry.Cameras` in float64, leading dims ``(C,)`` for a static rig
or ``(N, C)`` per frame, in the stored images' pixels. The checks report a camera whose ``K`` is singular or
whose last row is not ``[0, 0, 1]``, an ``R`` that is not a rotation, or a value that is not finite.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.data.problems import Problems
from s3k.data.tables import (
    CALIBRATION_COLUMNS,
    PER_FRAME_CALIBRATION_FILE,
    STATIC_CALIBRATION_FILE,
    Frames,
    Meta,
    locate,
    parse_float,
    read_csv,
    read_json,
)
from s3k.geometry import Cameras

# R is a rotation when max |R R^T - I| and |det R - 1| are below this (tolerates 6-digit rounding).
ROTATION_TOLERANCE = 1e-4
MAX_EXTENT = 1e9
"""Largest translation component of a camera, in any world unit (1000 km in millimetres): beyond it the file
is corrupted or mis-scaled, and projections lose their precision or overflow."""


def cameras_of(K: Any, dist: Any, R: Any, t: Any) -> Cameras:
    """Float64 ``Cameras`` of array-likes ``K (*L, 3, 3)``, ``dist (*L, 5)``, ``R (*L, 3, 3)``, ``t (*L, 3)``.

    Unlike ``Cameras.from_numpy`` this keeps NaN: a placeholder rig stands in for a calibration that failed
    its checks, so that ``s3k validate`` can go on to the images and the summary.
    """
    return Cameras(*(torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in (K, dist, R, t)))


def camera_tuple(calibration: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(K, dist, R, t)`` float64 arrays of a ``Cameras`` or of a ``(K, dist, R, t)`` sequence of
    array-likes."""
    if isinstance(calibration, Cameras):
        a = calibration.numpy()
        return a["K"], a["dist"], a["R"], a["t"]
    if isinstance(calibration, (tuple, list)) and len(calibration) == 4:
        K, dist, R, t = (np.asarray(x, dtype=np.float64) for x in calibration)
        return K, dist, R, t
    raise ValueError(f"calibration must be Cameras or (K, dist, R, t), got {type(calibration).__name__}")



def camera_defects(
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
    extent = np.abs(np.where(np.isfinite(t), t, 0.0)).max(axis=-1)
    for i in np.flatnonzero(finite["t"] & (extent > MAX_EXTENT)):
        out[i].append(("t", f"{t[i].tolist()} is beyond any rig (a component above {MAX_EXTENT:g} in any "
                            "unit: a corrupted or mis-scaled file)"))
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



def read_static_calibration(root: Path, meta: Meta, P: Problems, name: str = STATIC_CALIBRATION_FILE,
                            missing: str = "file missing (s3k.json says calibration is static)"
                            ) -> Cameras | None:
    """A rig file (``calibration.json``, or a session's under ``calibration/``) as ``Cameras (C,)``."""
    ok, data = read_json(root, name, missing, P)
    if not ok:
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
    defects = camera_defects(K, dist, R, t)
    for c, cam in enumerate(meta.cameras):
        if not isinstance(cams.get(cam), dict):
            continue
        for fld, message in defects[c]:
            if (c, fld) not in unparsed:
                P.error(name, f"cameras.{cam}.{fld}", message, camera=cam)
                ok = False
    return cameras_of(K, dist, R, t) if ok else None


def read_per_frame_calibration(
    root: Path, meta: Meta, frames: Frames, P: Problems
) -> Cameras | None:
    name = PER_FRAME_CALIBRATION_FILE
    table = read_csv(root, name, CALIBRATION_COLUMNS, P)
    if table is None:
        return None
    _, rows = table
    N, C = len(frames.ids), len(meta.cameras)
    values = np.full((N, C, 26), np.nan)
    lines = np.zeros((N, C), dtype=np.int64)
    numeric = CALIBRATION_COLUMNS[2:]
    n_errors = len(P.errors)
    try:  # fast path: numpy converts every number at once; any bad cell sends us to the per-cell messages
        parsed = np.array([[row[col] for col in numeric] for _, row in rows], dtype=np.float64)
    except ValueError:
        parsed = None
    for r, (line, row) in enumerate(rows):
        found = locate(name, line, row, frames, P, camera=meta.cameras)
        if found is None:
            continue
        frame, i, (c,) = found
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
            value = parse_float(row[col])
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
    defects = camera_defects(K.reshape(-1, 3, 3), dist.reshape(-1, 5), R.reshape(-1, 3, 3), t.reshape(-1, 3))
    column_of = {"K": "K00..K22", "dist": "k1..k3", "R": "R00..R22", "t": "tx..tz"}
    for flat, camera_found in enumerate(defects):
        if not present[flat]:
            continue
        i, c = divmod(flat, C)
        for fld, message in camera_found:
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
    return cameras_of(K, dist, R, t)
