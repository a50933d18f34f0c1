"""Values of a configuration from text: a field's value from a command-line string or a JSON/TOML value
(:func:`coerce`), and the flat table of a config file (:func:`read_config_file`); :mod:`s3k.config` builds
the configuration from them."""

from __future__ import annotations

import json
import types
import typing
from pathlib import Path
from typing import Any

from s3k.base.choices import Device, parse_device
from s3k.base.errors import UserError

__all__ = ["base_type", "coerce", "read_config_file"]


def base_type(tp: Any) -> tuple[Any, bool]:
    """(type without Optional, is_optional); a union with ``str`` (a ``Literal`` of named values that also
    takes other names) is ``str``; :data:`s3k.base.choices.Device` stays itself."""
    if tp == Device:
        return tp, False
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return (str if str in args else args[0]), len(args) < len(typing.get_args(tp))
    return tp, False


def coerce(tp: Any, value: Any, where: str) -> Any:
    """Convert ``value`` (from JSON/TOML or a command-line string) to the field type ``tp``.

    Raises:
        UserError: naming ``where`` (file and field) and the offending value.
    """
    base, optional = base_type(tp)
    if base == Device and value is not None:
        return parse_device(value, where)
    if value is None or (optional and isinstance(value, str) and value.lower() in ("none", "null")):
        if optional:
            return None
        raise UserError(f"{where}: null is not allowed")
    try:
        if typing.get_origin(base) is tuple:
            (inner, *_rest) = typing.get_args(base)
            if isinstance(value, str):
                value = [v for v in value.replace(" ", "").split(",") if v]
            return tuple(inner(v) for v in value)
        if base is bool:
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in ("1", "true", "yes", "on"):
                return True
            if isinstance(value, str) and value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError("expected a boolean")
        if base is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError("expected an integer")
            if isinstance(value, bool):
                raise ValueError("expected an integer")
            return int(value)
        if base is float:
            if isinstance(value, bool):
                raise ValueError("expected a number")
            return float(value)
        if base is str:
            if not isinstance(value, str):
                raise ValueError("expected a string")
            return value
        if typing.get_origin(base) is typing.Literal:
            if value not in typing.get_args(base):
                raise ValueError(f"expected one of {', '.join(map(str, typing.get_args(base)))}")
            return value
    except (TypeError, ValueError) as exc:
        raise UserError(f"{where}: invalid value {value!r} ({exc})") from None
    raise ValueError(f"{where}: unsupported field type {tp!r}")


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Read a flat table of field values from a ``.toml`` or ``.json`` file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"config file {path} does not exist")
    if path.suffix.lower() == ".toml":
        try:
            import tomllib
        except ModuleNotFoundError:  # Python < 3.11
            import tomli as tomllib  # type: ignore[no-redef]
        try:
            with open(path, "rb") as fh:
                data = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise UserError(f"config file {path}: not valid TOML ({exc})") from None
    elif path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise UserError(f"config file {path}: not valid JSON ({exc})") from None
    else:
        raise UserError(f"config file {path}: expected a .toml or .json file")
    if not isinstance(data, dict):
        raise UserError(f"config file {path}: expected a table of field names")
    return data
