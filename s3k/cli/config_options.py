"""Command-line options derived from a configuration dataclass (``s3k.config``): one ``--field-name`` per
field.

Options default to ``argparse.SUPPRESS``, so that only values given on the command line override the config
file (or, for ``train --resume``, the run's saved configuration).
"""

from __future__ import annotations

import argparse
import typing
from typing import Any, TypeVar

from s3k.base.choices import Device
from s3k.base.errors import UserError
from s3k.config import TrainConfig, config_from_dict, field_default, flat_values, leaf_fields
from s3k.config_files import base_type, coerce, read_config_file

C = TypeVar("C")


def add_config_arguments(parser: argparse.ArgumentParser, cls: type = TrainConfig, base: Any = None,
                         sections: tuple[str, ...] | None = None) -> None:
    """Add ``--config FILE`` and one ``--field-name value`` option per field of ``cls`` to ``parser``, one
    argument group per section; each option's help shows the field's documentation and its default.

    An option is spelled with dashes (``--rotation-deg``; a boolean ``--layout-fit/--no-layout-fit``). The
    field's own name (``--rotation_deg``, ``--no-layout_fit``) is accepted too, as a second option with the
    same ``dest`` that ``--help`` does not show (its action's ``alias_of`` names the shown spelling).

    ``base`` (a ``cls``) gives the defaults shown, where a command starts from other values than the
    class's (``config_from_args(args, cls, base)`` resolves them); ``sections`` limits the options to those
    sections. A field's ``metadata`` may name its ``metavar`` and ``nargs`` (values given as several
    words)."""
    group = parser.add_argument_group("configuration (defaults < --config file < command line)")
    group.add_argument("--config", metavar="FILE", default=None,
                       help="TOML or JSON file with a flat table of the fields below (default: none)")
    groups: dict[str | None, Any] = {None: group}
    shown_defaults = flat_values(base) if base is not None else None
    for section, f, tp in leaf_fields(cls):
        if sections is not None and section not in sections:
            continue
        if section is not None and section not in groups:
            groups[section] = parser.add_argument_group(f"configuration: {section.replace('_', '-')}")
        base, _ = base_type(tp)
        default = field_default(f) if shown_defaults is None else shown_defaults[f.name]
        shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
        bounds = f.metadata.get("range")
        allowed = f"; {bounds.describe()}" if bounds is not None and bounds.describe() else ""
        text = f"{f.metadata.get('help', '')} (default: {shown}{allowed})".replace("%", "%%")
        flag = f"--{f.name.replace('_', '-')}"
        if base is bool:
            kwargs: dict[str, Any] = dict(action=argparse.BooleanOptionalAction)
        else:
            is_tuple = typing.get_origin(base) is tuple
            named = typing.get_origin(base) is typing.Literal
            metavar = ("N,N,..." if is_tuple else "{" + ",".join(typing.get_args(base)) + "}" if named
                       else "DEVICE" if base == Device else getattr(base, "__name__", "V").upper())
            kwargs = dict(metavar=f.metadata.get("metavar", metavar), type=_parser(f, tp))
            if "nargs" in f.metadata:  # several words, each one value of the tuple
                kwargs.update(nargs=f.metadata["nargs"], type=str)
        groups[section].add_argument(flag, dest=f.name, default=argparse.SUPPRESS, help=text, **kwargs)
        if "_" in f.name:  # the field's own spelling is accepted too, not shown
            alias = groups[section].add_argument(f"--{f.name}", dest=f.name, default=argparse.SUPPRESS,
                                                 help=argparse.SUPPRESS, **kwargs)
            alias.alias_of = flag  # type: ignore[attr-defined]


def _parser(f, tp: Any):
    """The ``type=`` of a field's option: the text converted to the field's type and, for a number, held
    to the field's range, so that a value out of range is refused as the command line is parsed."""
    bounds = f.metadata.get("range")

    def parse(text: str) -> Any:
        try:
            value = coerce(tp, text, "value")
        except UserError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("value: ")) from None
        problem = bounds.problem(value) if bounds is not None and value is not None else None
        if problem is not None:
            raise argparse.ArgumentTypeError(f"{problem}, got {text!r}")
        return value

    parse.__name__ = getattr(base_type(tp)[0], "__name__", "value")
    if bounds is not None:
        parse.range = bounds  # type: ignore[attr-defined]
    return parse


def config_from_args(args: argparse.Namespace, cls: type[C], base: C | None = None) -> C:
    """Resolve defaults (or ``base``) < ``args.config`` file < explicit command-line options."""
    cfg = base if base is not None else cls()
    if getattr(args, "config", None):
        where = f"config file {args.config}"
        cfg = config_from_dict(cls, read_config_file(args.config), base=cfg, where=where)
    given = {f.name: getattr(args, f.name) for _, f, _ in leaf_fields(cls) if hasattr(args, f.name)}
    if given:
        cfg = config_from_dict(cls, given, base=cfg, where="command line")
    return cfg
