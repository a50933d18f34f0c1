"""Typed, documented configuration for training, loaded from a TOML/JSON file and command-line overrides.

Every field of :class:`TrainConfig` carries its documentation in ``metadata["help"]``; the same text is
shown by ``s3k train --help`` next to the field's default. Values are resolved in this order, later winning:

1. the dataclass defaults,
2. a config file (``--config FILE``, TOML or JSON, a flat table of field names),
3. command-line overrides ``--field value`` (``--field-name`` also works; booleans are ``--flag/--no-flag``).

Example:
    >>> cfg = TrainConfig()
    >>> cfg.alpha_at(0), cfg.alpha_at(cfg.warmup_steps + cfg.ramp_steps)
    (0.0, 0.5)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


def _f(default: Any, help: str) -> Any:
    """A dataclass field with a default and its documentation."""
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata={"help": help})
    return field(default=default, metadata={"help": help})


@dataclass
class TrainConfig:
    """Everything that defines a training run; written to ``RUN/config.json``.

    Defaults are sized for a 2-core CPU: 96-128 px images, a U-Net of about 100k parameters, heatmaps at
    stride 2 and a few thousand steps.
    """

    # --- schedule ---
    steps: int = _f(3000, "number of optimizer steps")
    batch_labelled: int = _f(4, "labelled frames per step (each frame gives C camera images)")
    batch_unlabelled: int = _f(4, "unlabelled frames per step for the self-supervised term")
    lr: float = _f(1e-3, "Adam learning rate at the start")
    lr_final: float = _f(0.05, "learning rate at the last step as a fraction of lr (cosine decay)")
    weight_decay: float = _f(1e-5, "lambda: weight of the squared L2 norm of non-bias parameters")
    grad_clip: float = _f(10.0, "clip the global gradient norm to this value (0: no clipping)")

    # --- self-supervision ---
    unsup: bool = _f(True, "use the self-supervised multi-view term; --no-unsup trains the labels-only "
                           "baseline (same network, no unlabelled batch)")
    alpha: float = _f(0.5, "weight of the self-supervised loss once ramped up (paper: 0.5)")
    warmup_steps: int = _f(750, "labels-only steps before the self-supervised term starts (alpha = 0); "
                                "avoids locking in a collapse from a random network")
    ramp_steps: int = _f(750, "steps over which alpha rises linearly from 0 to --alpha after the warm-up")

    # --- network and targets ---
    image_size: int = _f(0, "resize images so the longer side has this many pixels (0: keep the dataset's "
                            "size)")
    channels: tuple[int, ...] = _f((16, 32, 32, 32), "U-Net channels per level, level 0 at heatmap "
                                                     "resolution; len - 1 downsamplings by 2")
    res_blocks: int = _f(2, "residual blocks (3 convolutions each) at the U-Net's lowest resolution")
    norm: str = _f("batch", "normalization after each convolution: 'batch', 'group' or 'none'")
    stride: int = _f(2, "heatmap stride: one heatmap cell covers stride x stride image pixels")
    sigma: float = _f(1.5, "target Gaussian width in heatmap cells (sigma in image pixels is sigma * stride)")

    # --- augmentation (geometry stays exact: K <- M K) ---
    augment: bool = _f(True, "augment every image with a random similarity and photometric changes")
    rotation_deg: float = _f(180.0, "maximum in-plane rotation of the augmentation, degrees")
    scale: float = _f(0.2, "maximum relative scale change of the augmentation (0.2: x0.8 to x1.2)")
    shift_px: float = _f(10.0, "maximum shift of the augmentation along u and v, image pixels")
    brightness: float = _f(0.2, "maximum additive brightness change (images in [0, 1])")
    contrast: float = _f(0.2, "maximum relative contrast change")
    colour: float = _f(0.1, "maximum relative per-channel gain change")
    noise: float = _f(0.02, "maximum standard deviation of additive Gaussian pixel noise")

    # --- monitoring ---
    val_every: int = _f(250, "validate (metrics, collapse check, images) every this many steps (0: never)")
    val_frames: int = _f(16, "frames used for validation")
    val_split: str = _f("test", "split used for validation; falls back to 'unlabelled' when absent or empty")
    collapse_fraction: float = _f(0.3, "warn of a collapse when the mean pairwise distance of the "
                                       "triangulated keypoints falls below this fraction of the labelled "
                                       "layout's")
    log_every: int = _f(25, "write loss terms to TensorBoard every this many steps")
    checkpoint_every: int = _f(500, "write RUN/checkpoint.pt every this many steps (and at the end)")
    max_nonfinite: int = _f(20, "stop cleanly after this many consecutive steps with a non-finite loss")
    progress: bool = _f(True, "show a progress bar")

    # --- execution ---
    seed: int = _f(0, "random seed (batches, augmentation, initialization)")
    device: str = _f("auto", "'auto' (GPU when available), 'cpu', 'cuda' or 'cuda:N'")
    threads: int = _f(0, "torch intra-op threads (0: torch's default); on a shared CPU 1 is often fastest, "
                         "since threads waiting for a busy core stall every convolution")
    preload_mb: int = _f(2048, "load all images into memory when they take at most this many MiB")

    def alpha_at(self, step: int) -> float:
        """Weight of the self-supervised term at ``step``: 0 during the warm-up, then a linear ramp to alpha.

        Args:
            step: 0-based optimizer step.

        Returns:
            The alpha used at that step (always 0 for the labels-only baseline).
        """
        if not self.unsup or step < self.warmup_steps:
            return 0.0
        if self.ramp_steps <= 0:
            return float(self.alpha)
        return float(self.alpha) * min(1.0, (step - self.warmup_steps + 1) / self.ramp_steps)

    def sigma_px(self) -> float:
        """Target Gaussian width in image pixels."""
        return float(self.sigma) * int(self.stride)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when a value is out of range."""
        positive = ["steps", "batch_labelled", "stride", "lr", "sigma", "val_frames", "max_nonfinite",
                    "checkpoint_every", "log_every"]
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"config field {name!r} must be > 0, got {getattr(self, name)!r}")
        non_negative = [
            "batch_unlabelled", "alpha", "warmup_steps", "ramp_steps", "image_size", "weight_decay",
            "grad_clip", "res_blocks", "rotation_deg", "scale", "shift_px", "brightness", "contrast",
            "colour",
            "noise", "val_every", "threads", "preload_mb", "lr_final", "collapse_fraction",
        ]
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ValueError(f"config field {name!r} must be >= 0, got {getattr(self, name)!r}")
        if self.unsup and self.batch_unlabelled <= 0:
            raise ValueError("config field 'batch_unlabelled' must be > 0 unless --no-unsup is given")
        if not self.channels or any(c <= 0 for c in self.channels):
            raise ValueError(f"config field 'channels' must be positive integers, got {self.channels!r}")
        if self.scale >= 1:
            raise ValueError(f"config field 'scale' must be < 1, got {self.scale!r}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary of all fields."""
        out = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


# ----------------------------------------------------------------------------------------------------
# Generic dataclass <-> file / argparse plumbing (works for any dataclass with documented fields).


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _base_type(tp: Any) -> tuple[Any, bool]:
    """(type without Optional, is_optional)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0], len(args) < len(typing.get_args(tp))
    return tp, False


def coerce(tp: Any, value: Any, where: str) -> Any:
    """Convert ``value`` (from JSON/TOML or a command-line string) to the field type ``tp``.

    Raises:
        ValueError: naming ``where`` (file and field) and the offending value.
    """
    base, optional = _base_type(tp)
    if value is None or (optional and isinstance(value, str) and value.lower() in ("none", "null")):
        if optional:
            return None
        raise ValueError(f"{where}: null is not allowed")
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
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: invalid value {value!r} ({exc})") from None
    raise ValueError(f"{where}: unsupported field type {tp!r}")


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Read a flat table of field values from a ``.toml`` or ``.json`` file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist")
    if path.suffix.lower() == ".toml":
        try:
            import tomllib
        except ModuleNotFoundError:  # Python < 3.11
            import tomli as tomllib  # type: ignore[no-redef]
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    elif path.suffix.lower() == ".json":
        data = json.loads(path.read_text())
    else:
        raise ValueError(f"config file {path}: expected a .toml or .json file")
    if not isinstance(data, dict):
        raise ValueError(f"config file {path}: expected a table of field names")
    return data


def config_from_dict(cls: type, data: dict[str, Any], base: Any = None, where: str = "config") -> Any:
    """Build a ``cls`` instance from ``data`` over ``base`` (or the defaults); unknown keys are errors."""
    types_ = _field_types(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    values = dataclasses.asdict(base) if base is not None else {}
    for key, value in data.items():
        if key not in names:
            raise ValueError(f"{where}: unknown field {key!r}; known fields: {', '.join(sorted(names))}")
        values[key] = coerce(types_[key], value, f"{where}: field {key!r}")
    return cls(**values)


def add_config_arguments(parser: argparse.ArgumentParser, cls: type = TrainConfig) -> None:
    """Add ``--config FILE`` and one ``--field value`` option per field of ``cls`` to ``parser``.

    Options default to ``argparse.SUPPRESS`` so that only values given on the command line override the file;
    each option's help shows the field's documentation and its default.
    """
    types_ = _field_types(cls)
    group = parser.add_argument_group("configuration (defaults < --config file < command line)")
    group.add_argument("--config", metavar="FILE", default=None,
                       help="TOML or JSON file with a flat table of the fields below")
    for f in dataclasses.fields(cls):
        base, _ = _base_type(types_[f.name])
        if f.default is not dataclasses.MISSING:
            default = f.default
        else:
            default = f.default_factory()  # type: ignore[misc,operator]
        shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
        text = f"{f.metadata.get('help', '')} (default: {shown})".replace("%", "%%")
        flags = [f"--{f.name}"]
        if "_" in f.name:
            flags.append(f"--{f.name.replace('_', '-')}")
        if base is bool:
            group.add_argument(*flags, dest=f.name, action=argparse.BooleanOptionalAction,
                               default=argparse.SUPPRESS, help=text)
        else:
            is_tuple = typing.get_origin(base) is tuple
            metavar = "N,N,..." if is_tuple else getattr(base, "__name__", "V").upper()
            group.add_argument(*flags, dest=f.name, default=argparse.SUPPRESS, metavar=metavar, help=text)


def config_from_args(args: argparse.Namespace, cls: type = TrainConfig, base: Any = None) -> Any:
    """Resolve defaults (or ``base``) < ``args.config`` file < explicit command-line options."""
    cfg = base if base is not None else cls()
    if getattr(args, "config", None):
        data = read_config_file(args.config)
        cfg = config_from_dict(cls, data, base=cfg, where=f"config file {args.config}")
    overrides = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    if overrides:
        cfg = config_from_dict(cls, overrides, base=cfg, where="command line")
    return cfg


def explicit_overrides(args: argparse.Namespace, cls: type = TrainConfig) -> dict[str, Any]:
    """The fields given explicitly on the command line (raw values)."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
