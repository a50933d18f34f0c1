"""A calibration file of any format s3k reads -> :class:`s3k.data.rig.Rig`: :func:`read_calibration`.

The format is chosen by the content (and the name where the content is ambiguous): a pickle is DeepFly3D's
(:mod:`s3k.data.formats.deepfly3d`); XML with ``<cameras><camera>`` (a ``.qca.txt``) is Qualisys'
(:mod:`s3k.data.formats.qualisys`); a folder, a YAML file or XML of ``<opencv_storage>`` is OpenCV's
``FileStorage`` (JARVIS and others, :mod:`s3k.data.formats.opencv_calib`); anything else is read as anipose's
``calibration.toml`` (:mod:`s3k.data.formats.anipose`), which says so when it is not one.
"""

from __future__ import annotations

from pathlib import Path

from s3k.data.formats.anipose import read_anipose_calibration
from s3k.data.formats.deepfly3d import read_deepfly3d_calibration
from s3k.data.formats.opencv_calib import read_opencv_calibration
from s3k.data.formats.qualisys import read_qualisys_calibration
from s3k.data.rig import Rig

FORMATS = ("anipose", "qualisys", "opencv", "deepfly3d")


def calibration_format(path: str | Path) -> str:
    """The format of a calibration file or folder: one of :data:`FORMATS`."""
    path = Path(path)
    if path.is_dir():
        return "opencv"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found")
    with path.open("rb") as f:
        head = f.read(4096)
    name = path.name.lower()
    if head[:1] == b"\x80" or name.endswith((".pkl", ".pickle")):
        return "deepfly3d"
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if name.endswith(".qca.txt") or (text.startswith(b"<") and b"<cameras" in head and b"opencv" not in head):
        return "qualisys"
    if name.endswith((".yaml", ".yml", ".xml")) or text.startswith((b"%YAML", b"<?xml", b"<opencv_storage")):
        return "opencv"
    return "anipose"


def read_calibration(path: str | Path, units: str | None = None) -> Rig:
    """Read a calibration in any format of :data:`FORMATS` (see the module docstring).

    Cameras whose file gives no image size (JARVIS, DeepFly3D) have size 0 until
    :meth:`s3k.data.rig.Rig.with_sizes` fills it from the videos.

    Raises:
        FileNotFoundError: no such file. UserError: a bad file, naming it and the field.
    """
    kind = calibration_format(path)
    read = {"deepfly3d": read_deepfly3d_calibration, "qualisys": read_qualisys_calibration,
            "opencv": read_opencv_calibration}.get(kind, read_anipose_calibration)
    return read(path, units).checked(path)  # rotations that are rotations, finite values
