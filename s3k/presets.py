"""Named training configurations: the ones the docs recommend, each a set of :class:`s3k.config.TrainConfig`
fields and, for a coarse-to-fine detector, its two-pass options (``s3k train --preset NAME``; options given
on the command line or in ``--config`` win over the preset's).

``box-headline`` is the configuration of the box scene's headline figures (docs/results/accuracy): a coarse
pass at 96 px for 4000 steps at a learning rate of 1e-3 with rotations up to 180 degrees, a refining pass on
192 px crops for 2500 steps at 5e-3 with rotations up to 15 degrees and a narrow target, the box held to its
labelled layout (10%), views that miss the others' consensus by 6 px (at 128 px crops) left out of the
pseudo-labels, validation every 500 steps, and ``--precision auto``: the networks train in bfloat16 where the
hardware computes it natively. Until 2026-12-05 its refining pass ran 4000 steps at 1e-3, and until
2026-12-04 6000 steps in float32 (docs/results/accuracy/README.md).

``box-fast`` is the same with the refining pass on 128 px crops cut with a 10% margin (about 250 mm wide:
1.9 mm per crop pixel against the headline's 1.5), whose steps cost about half as much
(docs/results/accuracy/fast/box-fast). ``s3k demo`` trains it, to fit its time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from s3k.errors import UserError

__all__ = ["PRESETS", "Preset", "preset"]


@dataclass(frozen=True)
class Preset:
    """A named configuration.

    Attributes:
        description: one line for ``--help``.
        config: :class:`s3k.config.TrainConfig` fields (flat names) and their values.
        two_pass: the two-pass options (``coarse_size``, ``coarse_steps``, ``coarse_rotation``,
            ``crop_size``, ``margin``, ``extent``), or None for a one-pass detector.
    """

    description: str
    config: dict[str, Any] = field(default_factory=dict)
    two_pass: dict[str, Any] | None = None


# the box's network, target, read-out and schedule: both presets train them, on crops of their own size
_BOX = {"steps": 2500, "lr": 0.005, "outlier_px": 6.0, "pseudo_window": 5, "layout_tol": 0.1,
        "rotation_deg": 15.0, "sigma": 1.0, "val_every": 500, "precision": "auto"}
_BOX_COARSE = {"coarse_size": 96, "coarse_steps": 4000, "coarse_lr": 0.001, "coarse_rotation": 180.0}

PRESETS: dict[str, Preset] = {
    "box-headline": Preset(
        "the box headline: two passes (96 px, 192 px crops), rigid layout, narrow target",
        config=dict(_BOX),
        two_pass={**_BOX_COARSE, "crop_size": 192},
    ),
    "box-fast": Preset(
        "the box headline on 128 px crops with a 10% margin: a cheaper refining pass",
        config=dict(_BOX),
        two_pass={**_BOX_COARSE, "crop_size": 128, "margin": 0.1},
    ),
}


def preset(name: str) -> Preset:
    """The preset ``name``.

    Raises:
        UserError: no such preset, naming those there are.
    """
    if name not in PRESETS:
        raise UserError(f"--preset {name!r}: no such preset (presets: {', '.join(PRESETS)})")
    return PRESETS[name]
