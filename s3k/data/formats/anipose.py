"""anipose's ``calibration.toml``: :func:`read_anipose_calibration` and :func:`write_anipose_calibration`.

Each camera section (``[cam_0]``, ``[cam_1]``...) has ``name``, ``size = [W, H]``, ``matrix`` (3x3),
``distortions`` (5; fewer are zero-padded), ``rotation`` (Rodrigues, world->camera) and ``translation``. A
``[metadata]`` table, when present, describes the board. Every problem is a one-line
:class:`s3k.base.errors.UserError` naming the file, the section and the field.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_text
from s3k.data.rig import Rig, check_camera_name
from s3k.geometry import Cameras
from s3k.geometry.rotations import rodrigues_to_matrix

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CAMERA_FIELDS = ("size", "matrix", "distortions", "rotation", "translation")


def units_from_board(square_length: float | None) -> str:
    # anipose puts the world frame in the unit the user gave the board square in; its documentation and
    # every rig seen so far use millimetres (squares of 10-50). A sub-unit square length means metres.
    if square_length is None:
        return "unknown"
    return "m" if square_length < 1.0 else "mm"


def _numbers(path: Path, section: str, table: dict, key: str, shape: tuple[int, ...] | None) -> np.ndarray:
    """``table[key]`` as finite float64 of ``shape`` (any length when None), or a UserError naming it."""
    where = f"{path}: [{section}] {key}"
    if key not in table:
        raise UserError(f"{path}: section [{section}] has no field {key!r}")
    try:
        value = np.asarray(table[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where} must be numbers, got {table[key]!r}") from None
    if shape is None:
        value = value.reshape(-1)
    elif value.shape != shape:
        raise UserError(f"{where} has shape {value.shape}, expected {shape}")
    if not np.all(np.isfinite(value)):
        raise UserError(f"{where} has non-finite values: {table[key]!r}")
    return value


def _rotation(path: Path, section: str, table: dict) -> np.ndarray:
    """A section's ``rotation``: anipose's Rodrigues vector ``(3,)``, or the world->camera matrix ``(3, 3)``
    other tools write there (checked to be a rotation by :meth:`s3k.data.rig.Rig.checked`)."""
    value = _numbers(path, section, table, "rotation", None)
    if value.size == 3:
        return value
    if value.size == 9 and np.asarray(table["rotation"], dtype=np.float64).shape == (3, 3):
        return value.reshape(3, 3)
    raise UserError(f"{path}: [{section}] rotation has shape {np.asarray(table['rotation']).shape}, expected "
                    "(3,) (a Rodrigues vector) or (3, 3) (a rotation matrix)")


def _project_square_length(path: Path) -> float | None:
    """``[calibration] board_square_side_length`` of the anipose project ``config.toml`` in the calibration's
    folder or one of its three parents (anipose keeps ``calibration.toml`` in ``SESSION/calibration/``)."""
    for folder in [path.parent, *path.parent.parents][:4]:
        config = folder / "config.toml"
        if config.is_file() and config.resolve() != path.resolve():
            try:
                section = tomllib.loads(config.read_text(encoding="utf-8")).get("calibration", {})
            except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
                continue
            value = section.get("board_square_side_length") if isinstance(section, dict) else None
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                return float(value)
    return None


def _load_toml(path: Path, what: str) -> dict:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not {what} (not valid TOML: {exc})") from None


def _calibration_units(path: Path, metadata: dict) -> str:
    """The world unit of an anipose calibration: ``[metadata] units``, else that of the board's square length
    (``[metadata]``, a ``board.toml`` beside it, or the anipose project's ``config.toml``)."""
    if isinstance(metadata.get("units"), str):
        return metadata["units"]
    square = metadata.get("square_length")
    board = path.parent / "board.toml"
    if square is None and board.is_file():
        square = _load_toml(board, "a board.toml").get("square_length")
    if square is None:
        square = _project_square_length(path)
    try:
        return units_from_board(float(square) if square is not None else None)
    except (TypeError, ValueError):
        raise UserError(f"{path}: square_length must be a number, got {square!r}") from None


def read_anipose_calibration(path: str | Path, units: str | None = None) -> Rig:
    """Read an anipose ``calibration.toml``.

    Args:
        path: the TOML file.
        units: world length unit; by default ``[metadata] units`` if present (s3k writes it), else inferred
            from the board's ``square_length`` in ``[metadata]`` or in a ``board.toml`` beside the file
            or ``board_square_side_length`` in the anipose project's ``config.toml`` (in the file's folder or
            up to three folders above; anipose's world unit is the unit of the board's square length: ``"mm"``
            for lengths >= 1, ``"m"`` below), else ``"unknown"``.

    Returns:
        The rig, cameras in file order.

    Raises:
        FileNotFoundError: no such file.
        UserError: not an anipose calibration, or a bad value (naming the section and the field).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found")
    data = _load_toml(path, "an anipose calibration.toml")
    metadata = data.get("metadata", {})
    if not isinstance(metadata, dict):
        raise UserError(f"{path}: [metadata] must be a table")
    # A camera section has most of the camera fields; other tools' TOML files (a Pose2Sim Config.toml) have
    # sections that share a field name or two.
    sections = [k for k, v in data.items() if k != "metadata" and isinstance(v, dict)
                and sum(f in v for f in CAMERA_FIELDS) >= 3]
    if not sections:
        other = " (it looks like a Pose2Sim Config.toml; give the calibration file it produced)" \
            if "project" in data else ""
        raise UserError(
            f"{path}: not an anipose calibration: no camera sections ([cam_0], [cam_1], ... with "
            f"{', '.join(CAMERA_FIELDS)}){other}"
        )
    names: list[str] = []
    Ks, dists, rvecs, ts, sizes = [], [], [], [], []
    for section in sections:
        table = data[section]
        name = table.get("name", section)
        check_camera_name(name, f"{path}: [{section}] name")
        if name in names:
            raise UserError(f"{path}: [{section}] camera name {name!r} appears twice")
        if table.get("fisheye", False):
            raise UserError(f"{path}: [{section}] is a fisheye camera; s3k supports the pinhole model only")
        size = _numbers(path, section, table, "size", (2,))
        if np.any(size <= 0) or np.any(size != np.round(size)):
            raise UserError(f"{path}: [{section}] size must be two positive integers [W, H], got {size}")
        K = _numbers(path, section, table, "matrix", (3, 3))
        if abs(K[2, 2]) < 1e-12 or abs(np.linalg.det(K)) < 1e-12:
            raise UserError(f"{path}: [{section}] matrix is singular: {K.tolist()}")
        d = _numbers(path, section, table, "distortions", None)
        if d.size > 5 and np.any(d[5:] != 0):
            raise UserError(
                f"{path}: [{section}] distortions has {d.size} coefficients; "
                "s3k supports (k1, k2, p1, p2, k3)"
            )
        names.append(name)
        Ks.append(K / K[2, 2])
        dists.append(np.concatenate([d[:5], np.zeros(max(0, 5 - d.size))]))
        rvecs.append(_rotation(path, section, table))
        ts.append(_numbers(path, section, table, "translation", (3,)))
        sizes.append(size.astype(np.int64))
    units = _calibration_units(path, metadata) if units is None else units
    if any(r.shape == (3, 3) for r in rvecs):  # matrices in some sections: every rotation as a matrix
        rvecs = [r if r.shape == (3, 3) else rodrigues_to_matrix(torch.from_numpy(r)).numpy() for r in rvecs]
        for name, r in zip(names, rvecs):
            if not np.isfinite(r).all():
                raise UserError(f"{path}: camera {name}: its rotation vector gives no rotation")
    # Rodrigues vectors (C, 3) have the shape of t: from_numpy converts them to matrices.
    cams = Cameras.from_numpy(np.stack(Ks), np.stack(dists), np.stack(rvecs), np.stack(ts),
                              dtype=torch.float64)
    return Rig(names, cams, np.stack(sizes), units, dict(metadata)).checked(path)


def _toml_value(value: Any) -> str:
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


def write_anipose_calibration(path: str | Path, rig: Rig) -> None:
    """Write ``rig`` as an anipose ``calibration.toml`` (read back by :func:`read_anipose_calibration`): to a
    temporary file beside ``path``, renamed over it when complete, so that a write stopped at any moment (a
    full disk, a killed process) leaves the old file whole."""
    for name in rig.names:
        check_camera_name(name, f"{path}: camera")
    cams = rig.cameras.numpy()
    lines = []
    for c, name in enumerate(rig.names):
        rvec = cv2.Rodrigues(cams["R"][c])[0].reshape(3)
        lines += [
            f"[cam_{c}]",
            f"name = {_toml_value(name)}",
            f"size = {_toml_value([int(v) for v in rig.size[c]])}",
            f"matrix = {_toml_value([[float(v) for v in row] for row in cams['K'][c]])}",
            f"distortions = {_toml_value([float(v) for v in cams['dist'][c]])}",
            f"rotation = {_toml_value([float(v) for v in rvec])}",
            f"translation = {_toml_value([float(v) for v in cams['t'][c]])}",
            "",
        ]
    # anipose ignores unknown metadata keys; s3k records the world unit there so it survives a round trip.
    metadata = dict(rig.metadata)
    if rig.units != "unknown":
        metadata["units"] = rig.units
    lines.append("[metadata]")
    lines += [f"{k} = {_toml_value(v)}" for k, v in metadata.items()]
    lines.append("")
    atomic_write_text("\n".join(lines), path)
