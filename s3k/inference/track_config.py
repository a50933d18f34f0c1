"""Typed, documented settings of tracking (``s3k track``, ``s3k stream``, :func:`s3k.inference.track.track`).

:class:`TrackConfig` groups its fields in sections as :class:`s3k.config.TrainConfig` does (``filtering``,
``gates``, ``limbs``, ``readout``, ``chunks``, ``outputs``), each field with its help and range in its
metadata; code reads a field through its section (``cfg.chunks.batch``), and since field names are unique
the flat table of names is the configuration's form on the command line (``--filter-gate 5``:
``s3k.cli.config_options``), in a ``--config FILE`` and in ``--print-config``.

Example:
    >>> cfg = TrackConfig.from_flat(filter="none", batch=4)
    >>> cfg.chunks.batch, cfg.filter_settings().method
    (4, 'none')
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from s3k.base.choices import FilterMethod, MotionModel
from s3k.base.errors import UserError
from s3k.base.ranges import Range
from s3k.config import check_choice, config_from_dict, flat_values, leaf_fields
from s3k.inference.kalman import RANGES, FilterSettings
from s3k.readout import DEFAULT_MIN_WEIGHT

__all__ = ["TrackConfig"]


def _s(default: Any, help: str, metavar: str | None = None, nargs: str | None = None,
       within: Range | None = None, **bounds: Any) -> Any:
    """A field with a default, its documentation, for a number its :class:`s3k.base.ranges.Range` (as
    :mod:`s3k.config`'s fields carry them), and the option's ``metavar`` and ``nargs`` on the command
    line; ``within``: a range declared elsewhere (:data:`s3k.inference.kalman.RANGES`), in place of
    ``bounds``."""
    metadata: dict[str, Any] = {"help": help}
    if within is not None:
        metadata["range"] = within
    elif bounds or (isinstance(default, (int, float)) and not isinstance(default, bool)):
        metadata["range"] = Range(**bounds)
    metadata.update({k: v for k, v in (("metavar", metavar), ("nargs", nargs)) if v is not None})
    return field(default=default, metadata=metadata)


@dataclass
class FilteringConfig:
    """A Kalman filter in 3D per keypoint whose measurement noise comes from each detection's confidence and
    reprojection residual (docs/tracks.md)."""

    filter: FilterMethod = _s("kalman", "filter the 3D points over time (the raw points in "
                                                     "<stem>.raw.csv)")
    filter_model: MotionModel = _s(
        "velocity", "motion model of each keypoint: constant velocity or constant acceleration")
    filter_process_noise: float | None = _s(
        None, "standard deviation of the white noise driving the motion, world units per frame squared "
              "(cubed for acceleration) (none: fitted per keypoint by likelihood)", "Q",
        within=RANGES["process_noise"])
    filter_noise_scale: float | None = _s(None, "scale of the measurement noise (none: fitted per keypoint "
                                                "by likelihood)", "S", within=RANGES["noise_scale"])
    filter_noise_px: float | None = _s(None, "least reprojection residual a detection counts with, pixels "
                                             "(none: the keypoint's median residual)", "PX",
                                          within=RANGES["noise_px"])


@dataclass
class GatesConfig:
    """Jumps beyond the innovation gate are rejected and bridged, as are short gaps."""

    filter_gate: float = _s(4.0, "reject a point further than this many standard deviations from the "
                                 "prediction (0: never)", "SIGMAS", within=RANGES["gate"])
    filter_max_gap: int = _s(10, "bridge up to this many missing or rejected frames; after a longer gap the "
                                 "filter starts again", "FRAMES", within=RANGES["max_gap"])


@dataclass
class LimbsConfig:
    """A rigid object's layout and a skeleton's limb lengths hold the points as soft constraints."""

    filter_rigid: Literal["auto", "on", "off"] = _s(
        "auto", "hold the points to the rigid layout the run was trained with (--layout-tol); auto: when it "
                "has one")
    filter_layout_std: float | None = _s(None, "how far a point may stand off the rigid layout, world units "
                                               "(none: fitted)", "W", within=RANGES["layout_std"])
    filter_limbs: tuple[str, ...] | None = _s(
        None, "limbs (pairs of keypoints) whose lengths are held near their median over the track, or 'none' "
              "(none given: the skeleton the run recorded from its dataset, if any)", "A,B", "+")
    filter_limb_std: float | None = _s(None, "how far a limb's length may stand off its median, world units "
                                             "(none: its robust spread over the track)", "W",
                                          within=RANGES["limb_std"])


@dataclass
class ReadoutSettings:
    """Which views enter the triangulation."""

    min_weight: float = _s(DEFAULT_MIN_WEIGHT, "calibrated confidence a view needs to be used (0: every "
                                               "view, weighted by its confidence weight, as in training and "
                                               "'s3k evaluate'; 0.5 keeps the views of which about half or "
                                               "more lie within 2 sigma of the truth on the run's validation "
                                               "frames; a run trained before runs were calibrated compares "
                                               "its raw weight)",
                           ge=0, lt=1)


@dataclass
class ChunksConfig:
    """Which frames, and how many per forward pass."""

    batch: int = _s(8, "frames per forward pass", ge=1)
    start: int = _s(0, "first frame index", ge=0)
    stop: int | None = _s(None, "frame index to stop before (none: the end of the shortest video)", ge=0)


@dataclass
class OutputsConfig:
    """What is written beside the CSV, the doubt ranking and the JSON companions."""

    overlay: str | None = _s(None, "write DIR/<camera>.mp4 with the reprojected keypoints drawn; DIR is new, "
                                   "empty or an earlier overlay folder", "DIR")
    progress: bool = _s(True, "show a progress bar")


@dataclass(slots=True)
class TrackConfig:
    """Everything that defines how a recording is tracked, past the run, the rig and the files
    (module docstring)."""

    filtering: FilteringConfig = field(default_factory=FilteringConfig)
    gates: GatesConfig = field(default_factory=GatesConfig)
    limbs: LimbsConfig = field(default_factory=LimbsConfig)
    readout: ReadoutSettings = field(default_factory=ReadoutSettings)
    chunks: ChunksConfig = field(default_factory=ChunksConfig)
    outputs: OutputsConfig = field(default_factory=OutputsConfig)

    @classmethod
    def from_flat(cls, base: TrackConfig | None = None, where: str = "config", **values: Any) -> TrackConfig:
        """A configuration from flat field values over ``base`` (or the defaults), e.g.
        ``TrackConfig.from_flat(filter="none", batch=4)``; values are converted to the field types."""
        return config_from_dict(cls, values, base=base, where=where)

    def replace(self, **values: Any) -> TrackConfig:
        """A copy with the flat fields ``values`` changed."""
        return self.from_flat(base=self, **values)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready flat dictionary of all fields (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in flat_values(self).items()}

    def validate(self) -> TrackConfig:
        """Raise ``UserError`` naming the option of a value out of its range (the ranges declared with the
        fields; floats must be finite) or of a choice it does not offer; returns ``self``."""
        values = flat_values(self)
        for _, f, tp in leaf_fields(type(self)):
            bounds, value = f.metadata.get("range"), values[f.name]
            option = f"--{f.name.replace('_', '-')}"
            if bounds is not None and value is not None:
                bounds.check(value, option)
            check_choice(tp, value, option)
        if self.chunks.stop is not None and self.chunks.stop <= self.chunks.start:
            raise UserError(f"--start/--stop: need 0 <= start < stop, got start={self.chunks.start}, "
                            f"stop={self.chunks.stop}")
        self.limb_pairs()
        return self

    def filter_settings(self) -> FilterSettings:
        """The :class:`s3k.inference.kalman.FilterSettings` of the ``filtering``, ``gates`` and ``limbs``
        sections (``method="none"``: no filter)."""
        rigid = {"auto": None, "on": True, "off": False}[self.limbs.filter_rigid]
        f, g, limbs = self.filtering, self.gates, self.limbs
        return FilterSettings(method=f.filter, model=f.filter_model, process_noise=f.filter_process_noise,
                              noise_scale=f.filter_noise_scale, noise_px=f.filter_noise_px,
                              gate=g.filter_gate, max_gap=g.filter_max_gap, rigid=rigid,
                              layout_std=limbs.filter_layout_std, limb_std=limbs.filter_limb_std)

    @property
    def filtering_on(self) -> bool:
        """Whether the points are filtered over time."""
        return self.filtering.filter != "none"

    def limb_pairs(self) -> list[tuple[str, str]] | None:
        """The pairs of ``filter_limbs`` (``[]`` for ``none``), or None: the skeleton the run recorded."""
        if self.limbs.filter_limbs is None:
            return None
        if list(self.limbs.filter_limbs) == ["none"]:
            return []
        pairs = []
        for text in self.limbs.filter_limbs:
            a, sep, b = text.partition(",")
            if not sep or not a or not b or "," in b:
                raise UserError(f"--filter-limbs {text!r}: expected two keypoint names A,B")
            pairs.append((a, b))
        return pairs

