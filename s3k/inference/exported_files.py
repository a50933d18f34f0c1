"""The checks :func:`s3k.inference.export.load_exported` makes before it runs an exported detector: the
two-pass export's JSON, field by field, and the runtime (ONNX unless the caller asks for TorchScript, whose
files hold code)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from s3k.base.errors import UserError

__all__ = ["EXPORTED_TWO_PASS", "FORMATS", "runtime_of", "two_pass_doc"]

FORMATS = ("onnx", "torchscript")
EXPORTED_TWO_PASS = "s3k-exported-two-pass/1"


def two_pass_doc(path: Path) -> dict:
    """The ``.json`` of a two-pass export, checked: its format, the crop rule's finite positive extent and
    size, and the two pass files, plain names of files in its own folder.

    Raises:
        UserError: one line naming the file and the field.
    """

    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise UserError(f"{path}: not a two-pass export of s3k (not JSON: {str(exc).splitlines()[0]})"
                        ) from None
    if not isinstance(doc, dict) or doc.get("format") != EXPORTED_TWO_PASS:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise UserError(f"{path}: not a two-pass export of s3k (format {found!r}, expected "
                        f"{EXPORTED_TWO_PASS!r})")
    missing = [k for k in ("coarse", "fine", "extent", "size") if k not in doc]
    if missing:
        raise UserError(f"{path}: field(s) {', '.join(missing)} missing (written by s3k export?)")
    for key, positive in (("extent", True), ("size", True), ("margin", False)):
        value = doc.get(key, 0.0)
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or (positive and value <= 0) or (key == "size" and value != int(value)):
            raise UserError(f"{path}: field {key!r} is {value!r}; expected a finite "
                            + ("positive whole number" if key == "size" else "positive number" if positive
                               else "number"))
    folder = path.resolve().parent
    for key in ("coarse", "fine"):
        name = doc[key]
        target = (folder / str(name)).resolve() if isinstance(name, str) and name else None
        if target is None or Path(name).is_absolute() or target.parent != folder:
            raise UserError(f"{path}: field {key!r} is {name!r}; expected the name of a file beside it in "
                            f"{folder} (no folder, no '..')")
        if not target.is_file():
            raise UserError(f"{path}: field {key!r} names {name}, which is not in {folder}")
    return doc


def runtime_of(path: Path, asked: str | None, recorded: str | None) -> str:
    """The runtime to load ``path`` with: ONNX unless the caller asks for TorchScript (``fmt``), since a
    TorchScript file is a program, not only weights."""
    if asked is not None:
        if asked not in FORMATS:
            raise UserError(f"{path}: format {asked!r}; expected one of {', '.join(FORMATS)}")
        return asked
    kind = recorded or ("onnx" if path.suffix == ".onnx" else "torchscript")
    if kind != "onnx":
        raise UserError(f"{path} is a TorchScript export, which runs code from the file; load_exported runs "
                        "only ONNX unless asked", hint="pass fmt='torchscript' if you trust the file, or "
                        "export with --format onnx")
    return kind
