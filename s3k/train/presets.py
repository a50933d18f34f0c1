"""Named training configurations: the ones the docs recommend, each a whole :class:`s3k.config.TrainConfig`
(``s3k train --preset NAME``; options given on the command line or in ``--config`` win over the preset's;
``s3k train --preset NAME --print-config`` prints it resolved).

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

``box-precise`` is the headline with its refining pass on 256 px crops (about 1.1 mm per crop pixel against
1.5). On the same renders and CPU, over three seeds, S3K's median is 2.40 mm against the headline's 2.82,
lower in every seed, its RMS 3.61 mm against 4.44, at 12.8 CPU-minutes per model against 8.1
(docs/results/accuracy/crops-256).

``real-pretrained`` is the headline without the rigid layout (``--layout-tol 0``, the configuration the docs
give a real rig) on an ImageNet-pretrained EfficientNet-Lite0 encoder cut at stride 8, trained at a tenth of
each pass's learning rate (s3k's extra ``pretrained``). On the real recording's held-out stretch it lies
0.07 mm nearer the proofread labels than the same configuration from scratch, in each of three seeds, at about
three times the CPU; on the simulated box at ten labels it is 1.2 mm worse in median, on unseen mugs 3.2 mm;
on the plush toy 0.5 mm better in median and worse in RMS over seeds; on cable insertion 0.02 mm worse in
median (docs/results/accuracy/pretrained).
"""

from __future__ import annotations

from dataclasses import dataclass

from s3k.base.errors import UserError
from s3k.config import TrainConfig

__all__ = ["PRESETS", "Preset", "preset"]


@dataclass(frozen=True)
class Preset:
    """A named configuration: ``description`` (one line for ``--help``) and ``config``, the whole
    :class:`s3k.config.TrainConfig`."""

    description: str
    config: TrainConfig


# the box's network, target, read-out and schedule, both passes: the presets train them, on crops of their
# own size
_BOX = TrainConfig.from_flat(
    steps=2500, lr=0.005, outlier_px=6.0, pseudo_window=5, layout_tol=0.1, rotation_deg=15.0, sigma=1.0,
    val_every=500, precision="auto",
    two_pass=True, coarse_size=96, coarse_steps=4000, coarse_lr=0.001, coarse_rotation=180.0,
    where="preset")

PRESETS: dict[str, Preset] = {
    "box-headline": Preset(
        "the box headline: two passes (96 px, 192 px crops), rigid layout, narrow target",
        _BOX.replace(crop_size=192),
    ),
    "box-fast": Preset(
        "the box headline on 128 px crops with a 10% margin: a cheaper refining pass",
        _BOX.replace(crop_size=128, crop_margin=0.1),
    ),
    "box-precise": Preset(
        "the box headline on 256 px crops: a lower median at about 1.6x the CPU",
        _BOX.replace(crop_size=256),
    ),
    "real-pretrained": Preset(
        "the box headline without its rigid layout, on an ImageNet-pretrained encoder cut at 8: a real rig, "
        "about 3x the CPU",
        _BOX.replace(crop_size=192, layout_tol=0.0, encoder="efficientnet-lite0", encoder_stride=8,
                     encoder_lr=0.1),
    ),
}


def preset(name: str) -> TrainConfig:
    """A copy of the configuration of the preset ``name``.

    Raises:
        UserError: no such preset, naming those there are.
    """
    if name not in PRESETS:
        raise UserError(f"--preset {name!r}: no such preset (presets: {', '.join(PRESETS)})")
    return PRESETS[name].config.replace()
