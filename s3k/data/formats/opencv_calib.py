"""Calibrations in OpenCV's ``cv2.FileStorage`` files (YAML or XML): :func:`read_opencv_calibration`.

One file per camera, named by the file's stem, or a folder of such files (``.yaml``, ``.yml``, ``.xml``), one
camera each. Two layouts are read:

- JARVIS (and multicam-calibration's ``jarvis`` export): ``intrinsicMatrix`` and ``R`` stored transposed
  (MATLAB's convention), ``distortionCoefficients`` (k1, k2, p1, p2, k3) and ``T`` (3x1), world->camera.
- plain OpenCV names: ``camera_matrix`` / ``cameraMatrix`` / ``K``, ``dist_coeffs`` /
  ``distortion_coefficients`` / ``distCoeffs`` / ``D``, ``R`` (a 3x3 matrix or a Rodrigues vector) or
  ``rvec``, and ``T`` / ``t`` / ``tvec``, not transposed.

``image_width`` / ``image_height`` (or ``image_size``) give the image size when present; otherwise it is 0 and
the videos give it (:meth:`s3k.data.rig.Rig.with_sizes`). The unit of ``T`` is not recorded: ``units`` or
``"unknown"``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.data.rig import Rig
from s3k.geometry import Cameras

SUFFIXES = (".yaml", ".yml", ".xml")
_K = ("camera_matrix", "cameraMatrix", "K")
_DIST = ("dist_coeffs", "distortion_coefficients", "distCoeffs", "D", "dist")
_R = ("R", "rvec", "rotation")
_T = ("T", "t", "tvec", "translation")


def _node(fs, keys: tuple[str, ...]):
    for key in keys:
        node = fs.getNode(key)
        if not node.empty():
            return key, node
    return None, None


def _matrix(path: Path, key: str, node) -> np.ndarray:
    if node.isSeq():  # a plain YAML list
        value = np.array([node.at(i).real() for i in range(node.size())])
    else:  # an opencv-matrix
        value = node.mat()
        if value is None:
            raise UserError(f"{path}: {key} is not a matrix or a list of numbers")
    value = np.asarray(value, dtype=np.float64)
    if not np.isfinite(value).all():
        raise UserError(f"{path}: {key} has non-finite values")
    return value


def _read_one(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[int]]:
    head = path.read_bytes()[:65536]
    if b"<!DOCTYPE" in head or b"<!ENTITY" in head:  # OpenCV's own files never declare them
        raise UserError(f"{path}: an XML file with a DOCTYPE or entities is not an OpenCV calibration file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        reason = str(exc).strip().splitlines()[-1]
        raise UserError(f"{path}: not an OpenCV YAML/XML file ({reason})") from None
    try:
        if not fs.isOpened():
            raise UserError(f"{path}: not an OpenCV YAML/XML file")
        jarvis = not fs.getNode("intrinsicMatrix").empty()
        kkey, knode = ("intrinsicMatrix", fs.getNode("intrinsicMatrix")) if jarvis else _node(fs, _K)
        dkey, dnode = ("distortionCoefficients", fs.getNode("distortionCoefficients")) if jarvis else \
            _node(fs, _DIST)
        rkey, rnode = _node(fs, _R)
        tkey, tnode = _node(fs, _T)
        for node, names in ((knode, ("intrinsicMatrix", *_K)), (rnode, _R), (tnode, _T)):
            if node is None:
                raise UserError(f"{path}: not a camera calibration: no field {' / '.join(names)}")
        assert kkey and rkey and tkey
        k_flat = _matrix(path, kkey, knode).reshape(-1)
        if k_flat.size != 9:
            raise UserError(f"{path}: {kkey} has {k_flat.size} values, expected 3x3")
        K = k_flat.reshape(3, 3).T if jarvis else k_flat.reshape(3, 3)
        if abs(K[2, 2]) < 1e-12 or abs(np.linalg.det(K)) < 1e-12:
            raise UserError(f"{path}: {kkey} is singular: {K.tolist()}")
        d = np.zeros(5)
        if dnode is not None:
            raw = _matrix(path, str(dkey), dnode).reshape(-1)
            if raw.size > 5 and np.any(raw[5:] != 0):
                raise UserError(f"{path}: {dkey} has {raw.size} coefficients; s3k supports (k1, k2, p1, p2, "
                                "k3)")
            d[: min(5, raw.size)] = raw[:5]
        r_flat = _matrix(path, rkey, rnode).reshape(-1)
        if r_flat.size == 3:
            R = cv2.Rodrigues(r_flat)[0]
        elif r_flat.size == 9:
            R = r_flat.reshape(3, 3).T if jarvis else r_flat.reshape(3, 3)
        else:
            raise UserError(f"{path}: {rkey} has {r_flat.size} values, expected a 3x3 matrix or a Rodrigues "
                            "vector")
        if not np.isfinite(R).all():  # a Rodrigues vector too long for its angle's sine and cosine
            raise UserError(f"{path}: {rkey} {r_flat.tolist()} does not give a rotation")
        t = _matrix(path, tkey, tnode).reshape(-1)
        if t.size != 3:
            raise UserError(f"{path}: {tkey} has {t.size} values, expected 3")
        size = [0, 0]
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        if not w.empty() and not h.empty():
            size = [int(w.real()), int(h.real())]
        elif not fs.getNode("image_size").empty():
            size = [int(v) for v in _matrix(path, "image_size", fs.getNode("image_size")).reshape(-1)[:2]]
        return K / K[2, 2], d, R, t, size
    finally:
        fs.release()


def read_opencv_calibration(path: str | Path, units: str | None = None) -> Rig:
    """Read one camera file or a folder of them (see the module docstring); cameras sorted by name."""
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in SUFFIXES)
        if not files:
            raise UserError(f"{path}: folder has no OpenCV calibration files ({', '.join(SUFFIXES)})")
    elif path.is_file():
        files = [path]
    else:
        raise FileNotFoundError(f"{path}: calibration file not found")
    parts = [_read_one(f) for f in files]
    names = [f.name.split(".")[0] for f in files]
    K, dist, R, t = (np.stack([p[i] for p in parts]) for i in range(4))  # type: ignore[misc]
    cams = Cameras.from_numpy(K, dist, R, t, dtype=torch.float64)
    return Rig(names, cams, np.array([p[4] for p in parts]), units or "unknown", {"format": "opencv"})
