"""Typed, documented configuration for training, loaded from a TOML/JSON file and command-line overrides.

:class:`TrainConfig` groups its fields in sections (``model``, ``augmentation``, ``schedule``,
``self_supervision``, ``monitoring``, ``execution``, ``passes``: the two-pass options, ``backbone``: the
encoder), each a dataclass whose
fields carry their documentation in ``metadata["help"]``; ``s3k train --help`` shows that text next to the
field's default. Code reads a field through its section (``cfg.schedule.steps``), which a type checker
follows. Field names are unique across sections, so a configuration is also a flat table of field names: the
command line (``--steps``, ``--rotation-deg``), config files and ``RUN/config.json`` use that flat form
(:meth:`TrainConfig.from_flat`, :meth:`TrainConfig.replace`, :meth:`TrainConfig.to_dict`). Values are
resolved in this order, later winning:

1. the dataclass defaults,
2. a config file (``--config FILE``, TOML or JSON, a flat table of field names),
3. command-line overrides ``--field-name value``, the field's name with dashes (``--rotation-deg 15``; the
   field's own name, ``--rotation_deg``, also works; booleans are ``--flag/--no-flag``).

Example:
    >>> cfg = TrainConfig.from_flat(steps=100, unsup=False)
    >>> cfg.schedule.steps, cfg.self_supervision.unsup, cfg.alpha_at(10_000)
    (100, False, 0.0)
    >>> s = TrainConfig().self_supervision
    >>> TrainConfig().alpha_at(s.warmup_steps + s.ramp_steps)
    0.5
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from s3k.base.choices import Device, Norm, Precision, parse_device
from s3k.base.errors import UserError
from s3k.budget import check_config_fits
from s3k.config_fields import EncoderConfig
from s3k.config_fields import documented as _f
from s3k.config_files import base_type, coerce

C = TypeVar("C")

MAX_STEPS = 100_000_000
"""The most steps a training takes: the paper trained 150k; 1e8 steps are days at a millisecond a step."""
MAX_RES_BLOCKS = 100
"""The most residual blocks at the U-Net's lowest resolution (the paper: a few)."""


@dataclass
class ModelConfig:
    """The network and its heatmap targets."""

    image_size: int = _f(0, "resize images so the longer side has this many pixels (0: keep the dataset's "
                            "size)", ge=0)
    channels: tuple[int, ...] = _f((16, 32, 32, 32), "U-Net channels per level, level 0 at heatmap "
                                                     "resolution; len - 1 downsamplings by 2")
    res_blocks: int = _f(2, "residual blocks (3 convolutions each) at the U-Net's lowest resolution", ge=0,
                         le=MAX_RES_BLOCKS)
    norm: Norm = _f("batch", "normalization after each convolution: 'batch', 'group' or 'none'")
    stride: int = _f(2, "heatmap stride: one heatmap cell covers stride x stride image pixels",
                     one_of=(1, 2, 4))
    sigma: float = _f(1.5, "target Gaussian width in heatmap cells (sigma in image pixels is sigma * stride)",
                      gt=0)


@dataclass
class AugmentationConfig:
    """Random per-image augmentation; the geometry stays exact (``K <- M K``, ``s3k.train.augment``)."""

    augment: bool = _f(True, "augment every image with a random similarity and photometric changes")
    rotation_deg: float = _f(180.0, "maximum in-plane rotation of the augmentation, degrees", ge=0)
    scale: float = _f(0.2, "maximum relative scale change of the augmentation (0.2: x0.8 to x1.2)",
                      ge=0, lt=1)
    shift_px: float = _f(10.0, "maximum shift of the augmentation along u and v, image pixels", ge=0)
    stretch: float = _f(0.0, "maximum relative stretch of the augmentation along a random direction (0.3: "
                        "x0.7 to x1.3 along it), as a surface foreshortens from lower or higher cameras",
                        ge=0, lt=1)
    brightness: float = _f(0.2, "maximum additive brightness change (images in [0, 1])", ge=0)
    contrast: float = _f(0.2, "maximum relative contrast change", ge=0)
    colour: float = _f(0.1, "maximum relative per-channel gain change", ge=0)
    noise: float = _f(0.02, "maximum standard deviation of additive Gaussian pixel noise", ge=0)


@dataclass
class ScheduleConfig:
    """Optimization: steps, batches, learning rate."""

    steps: int = _f(3000, "number of optimizer steps", resumable=True, ge=1, le=MAX_STEPS)
    batch_labelled: int = _f(4, "labelled frames per step (each frame gives C camera images)", ge=1)
    batch_unlabelled: int = _f(4, "unlabelled frames per step for the self-supervised term", ge=0)
    lr: float = _f(1e-3, "Adam learning rate at the start", gt=0, le=1)
    lr_final: float = _f(0.05, "learning rate at the last step as a fraction of lr (cosine decay)", ge=0)
    weight_decay: float = _f(1e-5, "lambda: weight of the squared L2 norm of non-bias parameters", ge=0)
    grad_clip: float = _f(10.0, "clip the global gradient norm to this value (0: no clipping)", ge=0)


@dataclass
class SelfSupervisionConfig:
    """The self-supervised multi-view term and its schedule."""

    unsup: bool = _f(True, "use the self-supervised multi-view term; --no-unsup trains the labels-only "
                           "baseline (same network, no unlabelled batch)")
    alpha: float = _f(0.5, "weight of the self-supervised loss once ramped up (paper: 0.5)", ge=0)
    warmup_steps: int = _f(750, "labels-only steps before the self-supervised term starts (alpha = 0); "
                                "avoids locking in a collapse from a random network; when the warm-up and "
                                "ramp outlast --steps both shrink in proportion to end at the last step",
                           ge=0)
    ramp_steps: int = _f(750, "steps over which alpha rises linearly from 0 to --alpha after the warm-up",
                         ge=0)
    outlier_px: float = _f(6.0, "leave out of each pseudo-label the views whose detection misses the other "
                                "views' consensus by more than this many image pixels, one at a time (the "
                                "default is twice the target width; 0: every view, weighted by its "
                                "confidence, as in the paper)", ge=0)
    pseudo_window: int = _f(5, "read each view's detection for the pseudo-label as its heatmap's mean within "
                               "this many heatmap cells of the peak (0: the whole heatmap's mean, as in the "
                               "paper, which probability spread over the heatmap pulls towards its centre "
                               "and, trained on, draws the keypoints together)", ge=0)
    coord_weight: float = _f(0.0, "weight of a second term on every heatmap with a target: the distance from "
                                  "the whole heatmap's mean to the target's centre, in target widths; the KL "
                                  "measures the heatmap's shape, not where its mean falls, and this term "
                                  "trains the mean itself (0: off)", ge=0)
    teacher_ema: float = _f(0.0, "pseudo-labels from a teacher: a copy of the network whose weights follow "
                                 "the trained ones as an exponential moving average with this decay per "
                                 "step (e.g. 0.99); 0: from the trained network's own forward pass, as in "
                                 "the paper", ge=0, lt=1)
    layout_tol: float = _f(0.0, "rigid objects: leave out of the self-supervised term the pseudo-label "
                                "keypoints whose distances to the others differ from the labelled frames' "
                                "(median over them) by more than this fraction, e.g. 0.2, so that keypoints "
                                "detected together on one spot teach nothing, and at read-out look for such "
                                "a keypoint again where that layout puts it; 0: off (deformable objects)",
                            ge=0)
    layout_fit: bool = _f(False, "with --layout-tol: move the labelled layout onto each pseudo-label's kept "
                                 "keypoints (a rigid fit) and train towards its places, as the read-out "
                                 "does, instead of towards the triangulated points")


@dataclass
class MonitoringConfig:
    """Validation, logs and checkpoints."""

    val_every: int = _f(250, "validate (metrics, collapse check, images) every this many steps (0: never)",
                        resumable=True, ge=0)
    val_frames: int = _f(16, "frames used for validation", resumable=True, ge=1)
    val_split: str = _f("test", "split used for validation; falls back to 'unlabelled' when absent or empty",
                        resumable=True)
    collapse_fraction: float = _f(0.3, "warn of a collapse when the mean pairwise distance of the "
                                       "triangulated keypoints falls below this fraction of the labelled "
                                       "layout's", resumable=True, ge=0)
    log_every: int = _f(25, "write loss terms to TensorBoard every this many steps", resumable=True, ge=1)
    checkpoint_every: int = _f(500, "write RUN/checkpoint.pt every this many steps (and at the end)",
                               resumable=True, ge=1)
    max_nonfinite: int = _f(20, "stop cleanly after this many consecutive steps with a non-finite loss",
                            resumable=True, ge=1)
    progress: bool = _f(True, "show a progress bar", resumable=True)


@dataclass
class ExecutionConfig:
    """Randomness and where and how the computation runs."""

    seed: int = _f(0, "random seed (batches, augmentation, initialization)", ge=0)
    device: Device = _f("auto", "'auto' (GPU when available), 'cpu', 'cuda' or 'cuda:N'", resumable=True)
    threads: int = _f(0, "torch intra-op threads (0: torch's default); on a shared CPU 1 is often fastest, "
                         "since threads waiting for a busy core stall every convolution",
                      resumable=True, ge=0)
    precision: Precision = _f("float32", "the network's arithmetic in training: 'float32', 'bfloat16', or "
                                   "'auto' (bfloat16 autocast where the hardware computes it natively: a "
                                   "CUDA GPU with bfloat16, a CPU with AVX512-BF16 or AMX; else float32); "
                                   "the heatmap head, the losses and the read-out stay float32. bfloat16 "
                                   "trains the refining pass 1.65x faster on such a CPU for about 0.5 mm "
                                   "more median error on the box", resumable=True)
    preload_mb: int = _f(2048, "load all images into memory when they take at most this many MiB",
                         resumable=True, ge=0)


REFERENCE_CROP = 128
"""The default crop size (px) of a two-pass run, at which the refining pass takes its pixel-valued options as
given (:meth:`TrainConfig.refining` scales them by ``crop_size / REFERENCE_CROP``)."""


@dataclass
class TwoPassConfig:
    """Two passes (coarse-to-fine; docs/accuracy.md): a coarse detector on the whole image, crops of every
    view around its 3D estimate (a fixed extent in world units, so the object has one size in every crop)
    and a refining detector on the crops. The other options apply to both passes, ``--image-size`` to neither;
    :meth:`TrainConfig.coarse` and :meth:`TrainConfig.refining` are each pass's configuration."""

    two_pass: bool = _f(False, "train the coarse-to-fine detector (the options below; the others apply to "
                               "both passes, --image-size to neither)")
    coarse_size: int = _f(96, "the coarse pass's image size, longer side, px", ge=16)
    coarse_steps: int | None = _f(None, "the coarse pass's steps (none: --steps)", ge=1)
    coarse_rotation: float | None = _f(
        None, "the coarse pass's augmentation rotation range in degrees (none: --rotation-deg), e.g. 180 "
              "with --rotation-deg 15: a coarse pass that finds the object in any pose and a precise "
              "refining pass",
        ge=0)
    coarse_stride: int | None = _f(
        None, "the coarse pass's heatmap stride, 1, 2 or 4 (none: --stride), e.g. 2 with --stride 4: a "
              "coarse pass that places the crops well under a cheaper refining pass", ge=1, le=4)
    coarse_lr: float | None = _f(
        None, "the coarse pass's learning rate (none: --lr), e.g. to train a refining pass at another --lr "
              "on a finished coarse pass", gt=0, le=1)
    crop_size: int = _f(REFERENCE_CROP, f"crop size in pixels, the refining pass's input; the refining pass "
                                        f"scales --outlier-px, --shift-px and --pseudo-window by "
                                        f"PX/{REFERENCE_CROP} so they keep their size in the scene", ge=16)
    crop_margin: float = _f(0.3, "crop side = 2 x (largest distance of a labelled keypoint from the middle "
                                 "of its frame's keypoints) x (1 + F)", ge=0)
    crop_extent: float | None = _f(None, "crop side in world units at the estimate's depth (none: from the "
                                         "labels with --crop-margin)", gt=0)
    keep_crops: bool = _f(False, "also write the refining pass's crops as a dataset folder, RUN/crops (they "
                                 "are cut and used in memory otherwise)", resumable=True)


def _section(cls: type, help: str) -> Any:
    return field(default_factory=cls, metadata={"help": help})


@dataclass(slots=True)
class TrainConfig:
    """Everything that defines a training run; written (flat) to ``RUN/config.json``.

    Defaults are sized for a 2-core CPU: 96-128 px images, a U-Net of about 100k parameters, heatmaps at
    stride 2 and a few thousand steps. Read a field through its section, ``cfg.schedule.steps``; since field
    names are unique across sections, build one from flat values with :meth:`from_flat` and change fields
    with :meth:`replace`.
    """

    model: ModelConfig = _section(ModelConfig, "network and targets")
    augmentation: AugmentationConfig = _section(AugmentationConfig, "augmentation")
    schedule: ScheduleConfig = _section(ScheduleConfig, "schedule")
    self_supervision: SelfSupervisionConfig = _section(SelfSupervisionConfig, "self-supervision")
    monitoring: MonitoringConfig = _section(MonitoringConfig, "monitoring")
    execution: ExecutionConfig = _section(ExecutionConfig, "execution")
    passes: TwoPassConfig = _section(TwoPassConfig, "two passes")
    backbone: EncoderConfig = _section(EncoderConfig, "encoder")

    @classmethod
    def from_flat(cls, base: TrainConfig | None = None, where: str = "config", **values: Any) -> TrainConfig:
        """A configuration from flat field values over ``base`` (or the defaults), e.g.
        ``TrainConfig.from_flat(steps=100, unsup=False)``; values are checked and converted to the field
        types (a list gives a tuple); an unknown name raises ``ValueError`` naming it and ``where``."""
        return config_from_dict(cls, values, base=base, where=where)

    def replace(self, **values: Any) -> TrainConfig:
        """A copy with the flat fields ``values`` changed."""
        return self.from_flat(base=self, **values)

    def unsup_schedule(self) -> tuple[int, int]:
        """The warm-up and ramp steps this run uses: ``--warmup-steps`` and ``--ramp-steps``, unless together
        they outlast ``--steps``; then both shrink in proportion to end at the last step, so that the
        self-supervised term switches on in every S3K run (with the defaults, 750 + 750, a 200-step run warms
        up for 100 steps and ramps over the last 100).

        Example:
            >>> TrainConfig.from_flat(steps=200).unsup_schedule(), TrainConfig().unsup_schedule()
            ((100, 100), (750, 750))
        """
        s = self.self_supervision
        warmup, ramp, steps = int(s.warmup_steps), int(s.ramp_steps), int(self.schedule.steps)
        if warmup + ramp <= steps:
            return warmup, ramp
        scaled = steps * warmup // (warmup + ramp)
        return scaled, steps - scaled

    def coarse(self) -> TrainConfig:
        """The coarse pass's configuration: this one on the whole image at ``coarse_size`` px, with the
        coarse pass's own steps, rotation, stride and learning rate where they are set (a one-pass
        configuration: its two-pass section is the defaults)."""
        p = self.passes
        view = self.replace(image_size=p.coarse_size, steps=p.coarse_steps or self.schedule.steps,
                            rotation_deg=(self.augmentation.rotation_deg if p.coarse_rotation is None
                                          else p.coarse_rotation),
                            stride=self.model.stride if p.coarse_stride is None else p.coarse_stride,
                            lr=self.schedule.lr if p.coarse_lr is None else p.coarse_lr)
        return dataclasses.replace(view, passes=TwoPassConfig())

    def refining(self, crop_size: int | None = None) -> TrainConfig:
        """The refining pass's configuration: this one on ``crop_size`` px crops (default ``--crop-size``),
        its pixel-valued tolerances scaled by ``crop_size / REFERENCE_CROP`` (a one-pass configuration).

        The crop covers a fixed extent of the scene, so a crop pixel is ``extent / crop_size`` world units:
        the same ``--outlier-px`` would leave out of the pseudo-labels views half as far off at twice the crop
        size, and ``--shift-px`` and ``--pseudo-window`` would shrink in the scene alike. Scaled, they keep
        their size in the scene and ``--crop-size`` changes the resolution alone. ``--sigma`` is not scaled:
        a finer target is what a finer crop is for.
        """
        k = (self.passes.crop_size if crop_size is None else crop_size) / REFERENCE_CROP
        s, shift = self.self_supervision, self.augmentation.shift_px
        view = self.replace(image_size=0, outlier_px=s.outlier_px * k, shift_px=shift * k,
                            pseudo_window=max(1, round(s.pseudo_window * k)) if s.pseudo_window else 0)
        return dataclasses.replace(view, passes=TwoPassConfig())

    def alpha_at(self, step: int) -> float:
        """Weight of the self-supervised term at ``step``: 0 during the warm-up, then a linear ramp to alpha
        (the warm-up and ramp of :meth:`unsup_schedule`).

        Args:
            step: 0-based optimizer step.

        Returns:
            The alpha used at that step (always 0 for the labels-only baseline).
        """
        s = self.self_supervision
        warmup, ramp = self.unsup_schedule()
        if not s.unsup or step < warmup:
            return 0.0
        if ramp <= 0:
            return float(s.alpha)
        return float(s.alpha) * min(1.0, (step - warmup + 1) / ramp)

    def sigma_px(self) -> float:
        """Target Gaussian width in image pixels."""
        return float(self.model.sigma) * int(self.model.stride)

    def validate(self) -> None:
        """Raise ``UserError`` naming the field when a value is out of its range (the ranges declared with
        the fields; floats must be finite) or the fields contradict each other."""
        values = flat_values(self)
        for _, f, tp in leaf_fields(type(self)):
            bounds, value = f.metadata.get("range"), values[f.name]
            if bounds is not None and value is not None:
                bounds.check(value, f"config field {f.name!r}")
            check_choice(tp, value, f"config field {f.name!r}")
        if self.self_supervision.unsup and self.schedule.batch_unlabelled <= 0:
            raise UserError("config field 'batch_unlabelled' must be > 0 unless --no-unsup is given")
        if not self.model.channels or any(c <= 0 for c in self.model.channels):
            raise UserError(f"config field 'channels' must be positive integers, got {self.model.channels!r}")
        if self.passes.coarse_stride not in (None, 1, 2, 4):
            raise UserError(f"config field 'coarse_stride': the coarse pass's heatmap stride must be 1, 2 or "
                            f"4, got {self.passes.coarse_stride}", hint="pass --coarse-stride 1, 2 or 4")
        if self.passes.two_pass:
            if self.model.image_size:
                raise UserError("--image-size does not apply to --two-pass",
                                hint="set the coarse pass's size with --coarse-size and the crops' with "
                                     "--crop-size")
            self.coarse().validate()
            self.refining().validate()
        check_config_fits(self)  # a network that cannot fit in memory, whatever the dataset

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready flat dictionary of all fields (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in flat_values(self).items()}

    def with_options(self, argv: Sequence[str], where: str = "options") -> TrainConfig:
        """A copy with the ``s3k train`` configuration options ``argv`` applied (``["--steps", "100",
        "--no-unsup"]``, ``--field=value`` too): the inverse of :meth:`to_argv`, for options kept as text.

        Raises:
            UserError: an option that is not a field's, or one without its value, naming ``where``.
        """
        leaves = {f.name: tp for _, f, tp in leaf_fields(type(self))}
        values: dict[str, Any] = {}
        tokens = iter(argv)
        for token in tokens:
            name, eq, text = token.removeprefix("--").replace("-", "_").partition("=")
            flag = token.partition("=")[0]
            if not token.startswith("--"):
                raise UserError(f"{where}: {token!r} is not an option (--field-name value)")
            if name.startswith("no_") and leaves.get(name[3:]) is bool and not eq:
                values[name[3:]] = False
            elif leaves.get(name) is bool and not eq:
                values[name] = True
            elif name in leaves:
                value = text if eq else next(tokens, None)
                if value is None:
                    raise UserError(f"{where}: {flag} needs a value")
                values[name] = value
            else:
                raise UserError(f"{where}: unknown option {flag}", hint="give TrainConfig fields as options")
        return self.from_flat(base=self, where=where, **values)

    def to_argv(self) -> list[str]:
        """The ``s3k train`` options that give this configuration: one per field that differs from its
        default (``["--steps", "100", "--no-unsup"]``), for a training run in another process."""
        out: list[str] = []
        values = flat_values(self)
        for _, f, _ in leaf_fields(type(self)):
            value = values[f.name]
            if value != field_default(f):
                out += option_argv(f.name, value)
        return out


def check_choice(tp: Any, value: Any, where: str) -> None:
    """Refuse a value of a ``Literal`` field that is not one of its choices, or a device that is not one, in
    one line naming ``where``: the check of a configuration built in Python, whose values no parser saw."""
    base = base_type(tp)[0]
    if base == Device:
        parse_device(value, where)
    elif typing.get_origin(base) is typing.Literal and value not in typing.get_args(base):
        raise UserError(f"{where} must be one of {', '.join(map(str, typing.get_args(base)))}, got {value!r}")


def option_argv(name: str, value: Any) -> list[str]:
    """The command-line option that sets the field ``name`` to ``value`` (``["--layout-tol", "0.2"]``,
    ``["--no-layout-fit"]``, ``["--coarse-steps", "none"]``)."""
    flag = "--" + name.replace("_", "-")
    if isinstance(value, bool):
        return [flag if value else "--no-" + flag[2:]]
    if value is None:
        return [flag, "none"]
    return [flag, ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)]


# ----------------------------------------------------------------------------------------------------
# Generic dataclass <-> file / command-line plumbing. A configuration class is a dataclass whose fields are
# either documented values or sections (dataclasses of documented values); leaves are addressed by their
# (unique) names.


def _is_section(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def leaf_fields(cls: type) -> list[tuple[str | None, dataclasses.Field, Any]]:
    """``(section name or None, field, type)`` of every value field of ``cls``, sections expanded."""
    out: list[tuple[str | None, dataclasses.Field, Any]] = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if _is_section(tp):
            inner = typing.get_type_hints(tp)
            out.extend((f.name, g, inner[g.name]) for g in dataclasses.fields(tp))
        else:
            out.append((None, f, tp))
    return out


def flat_values(cfg: Any) -> dict[str, Any]:
    """The leaf values of a configuration, by field name."""
    return {f.name: getattr(getattr(cfg, s) if s else cfg, f.name) for s, f, _ in leaf_fields(type(cfg))}


def resumable_fields(cls: type = TrainConfig) -> set[str]:
    """Names of the fields ``--resume`` may change."""
    return {f.name for _, f, _ in leaf_fields(cls) if f.metadata.get("resumable")}


def field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory()  # type: ignore[misc,operator]


def default_of(name: str, cls: type = TrainConfig) -> Any:
    """The default of the field ``name`` of ``cls``, for settings elsewhere that start from it."""
    for _, f, _ in leaf_fields(cls):
        if f.name == name:
            return field_default(f)
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def config_from_dict(cls: type[C], data: dict[str, Any], base: C | None = None, where: str = "config") -> C:
    """Build a ``cls`` instance from the flat table ``data`` over ``base`` (or the defaults).

    A value may also be given inside its section (``{"schedule": {"steps": 10}}``). Unknown names raise
    ``UserError`` naming ``where`` and the field; values are converted to the field types.
    """
    leaves = {f.name: (s, tp) for s, f, tp in leaf_fields(cls)}
    sections = {s for s, _, _ in leaf_fields(cls) if s}
    flat: dict[str, Any] = {}
    for key, value in data.items():
        if key in sections and isinstance(value, dict):
            flat.update(value)
        else:
            flat[key] = value
    values = flat_values(base) if base is not None else {}
    for key, value in flat.items():
        if key not in leaves:
            raise UserError(f"{where}: unknown field {key!r}; known fields: {', '.join(sorted(leaves))}")
        values[key] = coerce(leaves[key][1], value, f"{where}: field {key!r}")
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(typing.cast(Any, cls)):
        if _is_section(hints[f.name]):
            inner = {g.name: values[g.name] for g in dataclasses.fields(hints[f.name]) if g.name in values}
            kwargs[f.name] = hints[f.name](**inner)
        elif f.name in values:
            kwargs[f.name] = values[f.name]
    return cls(**kwargs)
