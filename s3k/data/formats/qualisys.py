"""Qualisys calibrations exported as ``.qca.txt`` (an XML file, the layout Pose2Sim converts):
:func:`read_qualisys_calibration`.

Each ``cameras/camera`` element (name: its ``serial``) has ``fov_video`` (``left``, ``top``, ``right``,
``bottom``: the inclusive pixel range of the video), ``intrinsic`` (``focalLengthU/V``, ``centerPointU/V``,
``radialDistortion1/2``, ``tangentalDistortion1/2``, in 1/64 pixel of the sensor) and ``transform`` (``x, y,
z`` the camera position in mm, ``r11 .. r33`` its orientation). The conversion to the OpenCV model is
Pose2Sim's: the principal point is shifted by the video window's corner, the orientation is inverted to a
world->camera rotation and turned by 180 degrees about the camera's x axis (Qualisys cameras look along -z
with y up). ``video_resolution="720p"`` and the like scale a 1080p calibration to the recorded size. The world
unit stays Qualisys' millimetre.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.data.rig import Rig
from s3k.geometry import Cameras


def _attr(path: Path, element: ET.Element, serial: str, key: str) -> float:
    value = element.get(key)
    if value is None:
        raise UserError(f"{path}: camera {serial!r} <{element.tag}> has no attribute {key!r}")
    try:
        return float(value)
    except ValueError:
        raise UserError(f"{path}: camera {serial!r} <{element.tag}> {key}={value!r} is not a number") \
            from None


def read_qualisys_calibration(path: str | Path, units: str | None = None) -> Rig:
    """Read a Qualisys ``.qca.txt`` calibration (see the module docstring); cameras in file order."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise UserError(f"{path}: not a Qualisys .qca.txt calibration (not valid XML: {exc})") from None
    cameras = root.findall(".//cameras/camera")
    if not cameras:
        raise UserError(f"{path}: not a Qualisys calibration: no <cameras><camera> elements")
    flip = np.diag([1.0, -1.0, -1.0])
    names: list[str] = []
    Ks: list[np.ndarray] = []
    dists: list[list[float]] = []
    Rs: list[np.ndarray] = []
    ts: list[np.ndarray] = []
    sizes: list[list[int]] = []
    for cam in cameras:
        serial = cam.get("serial") or f"camera_{len(names)}"
        parts = {tag: cam.find(tag) for tag in ("fov_video", "intrinsic", "transform")}
        missing = [tag for tag, el in parts.items() if el is None]
        if missing:
            raise UserError(f"{path}: camera {serial!r} has no <{missing[0]}> element")
        fov, intr, tr = parts["fov_video"], parts["intrinsic"], parts["transform"]
        assert fov is not None and intr is not None and tr is not None
        resolution = cam.get("video_resolution")
        scale = 1.0
        if resolution:
            try:
                scale = int(resolution.rstrip("pP")) / 1080
            except ValueError:
                raise UserError(f"{path}: camera {serial!r} video_resolution={resolution!r} is not like "
                                "'1080p'") from None
        left, top = _attr(path, fov, serial, "left"), _attr(path, fov, serial, "top")
        W = (_attr(path, fov, serial, "right") - left + 1) * scale
        H = (_attr(path, fov, serial, "bottom") - top + 1) * scale
        a = {k: _attr(path, intr, serial, k) / 64 for k in (
            "focalLengthU", "focalLengthV", "centerPointU", "centerPointV", "radialDistortion1",
            "radialDistortion2", "tangentalDistortion1", "tangentalDistortion2")}
        K = np.array([[a["focalLengthU"] * scale, 0.0, (a["centerPointU"] - left) * scale],
                      [0.0, a["focalLengthV"] * scale, (a["centerPointV"] - top) * scale],
                      [0.0, 0.0, 1.0]])
        orient = np.array([[_attr(path, tr, serial, f"r{i}{j}") for j in (1, 2, 3)] for i in (1, 2, 3)])
        position = np.array([_attr(path, tr, serial, k) for k in ("x", "y", "z")])
        R = flip @ orient
        names.append(serial)
        Ks.append(K)
        dists.append([a["radialDistortion1"], a["radialDistortion2"], a["tangentalDistortion1"],
                      a["tangentalDistortion2"], 0.0])
        Rs.append(R)
        ts.append(-R @ position)
        sizes.append([round(W), round(H)])
    if len(set(names)) != len(names):
        raise UserError(f"{path}: camera serials repeat: {names}")
    cams = Cameras.from_numpy(np.stack(Ks), np.array(dists), np.stack(Rs), np.stack(ts), dtype=torch.float64)
    return Rig(names, cams, np.array(sizes), units or "mm", {"format": "qualisys"})
