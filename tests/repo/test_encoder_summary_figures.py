"""The encoder's summary in docs/training.md and in the ``real-pretrained`` preset's docstring (what a step
costs, what the encoder buys per scene against the scratch U-Net) reads as the committed JSON it comes from,
to the digits shown (the rules of ``helpers.figures``)."""

from __future__ import annotations

from helpers.figures import Figures, Getter, loader, mismatches, page_mismatches, value_at
from helpers.paths import REPO as ROOT
from helpers.pretrained_files import (
    CURVE,
    CURVE_5,
    CURVE_20,
    INSERTION,
    INSERTION_HERE,
    MUGS,
    MUGS_HERE,
    PLUSH,
    PLUSH_HERE,
    REAL,
    SCRATCH_HERE,
    STEP,
)


def _step_ratio(size: int, stride: int) -> Getter:
    """The encoder's CPU per training step over the U-Net's, at ``size`` px, cut at ``stride``."""
    def get(load) -> float:
        rows = [r for r in load(STEP)["rows"] if r["size"] == size
                and r["train_options"].endswith(f"--encoder-stride {stride}")]
        assert len(rows) == 1, (size, stride)
        return rows[0]["cpu_over_unet"]
    return get


def _median_gap(encoder: str, scratch: str, path: str) -> Getter:
    """The encoder's mean S3K median over seeds less the scratch model's (positive: the encoder is worse)."""
    return lambda load: value_at(load(encoder), f"{path}/mean") - value_at(load(scratch), f"{path}/mean")


# against the scratch models trained on the encoder's machine
BOX_WORSE = ("d1", _median_gap(CURVE, SCRATCH_HERE, "curve/s3k/10/median_mm"))
BOX_5_WORSE = ("d1", _median_gap(CURVE_5, SCRATCH_HERE, "curve/s3k/5/median_mm"))
BOX_20_WORSE = ("d1", _median_gap(CURVE_20, SCRATCH_HERE, "curve/s3k/20/median_mm"))
MUGS_WORSE = ("d1", _median_gap(MUGS, MUGS_HERE, "s3k/median_mm"))
PLUSH_BETTER = ("d1", lambda load: -_median_gap(PLUSH, PLUSH_HERE, "s3k/median_mm")(load))
INSERTION_WORSE = ("d2", _median_gap(INSERTION, INSERTION_HERE, "s3k/median_mm"))
REAL_NEARER = ("d2", lambda load: -load(REAL)["mean_paired_diff_mm"])

TRAINING: Figures = [
    ("cut at stride 8 costs about {} times the U-Net's CPU time at 192 px and {} times at 96 px, cut at 16 {}"
     " times", [("d0", _step_ratio(192, 8)), ("d1", _step_ratio(96, 8)), ("d0", _step_ratio(192, 16))]),
    ("on the simulated box at ten labels S3K with it is {} mm worse in median than from scratch, in every"
     " seed ({} mm at five, {} at twenty)", [BOX_WORSE, BOX_5_WORSE, BOX_20_WORSE]),
    ("on unseen mugs {} mm worse in every seed", [MUGS_WORSE]),
    ("on the plush toy {} mm better in median in every seed", [PLUSH_BETTER]),
    ("cable insertion {} mm worse in median in every seed, at about {} mm",
     [INSERTION_WORSE, ("d2", lambda load: load(INSERTION_HERE)["s3k"]["median_mm"]["mean"])]),
    ("it lies {} mm nearer the proofread labels, in every seed", [REAL_NEARER]),
]

PRESET: Figures = [
    ("it lies {} mm nearer the proofread labels than the same configuration from scratch", [REAL_NEARER]),
    ("on the simulated box at ten labels it is {} mm worse in median, on unseen mugs {} mm;",
     [BOX_WORSE, MUGS_WORSE]),
    ("on the plush toy {} mm better in median", [PLUSH_BETTER]),
    ("on cable insertion {} mm worse in median", [INSERTION_WORSE]),
]

PAGES = {"docs/training.md": TRAINING, "s3k/train/presets.py": PRESET}


def test_every_encoder_summary_figure_equals_its_json():
    assert page_mismatches(PAGES, loader()) == {page: [] for page in PAGES}


def test_a_changed_mugs_median_fails_in_both_places():
    load = loader()
    shown = f"{MUGS_WORSE[1](load) + 1.0:.1f}"  # what the edited JSON gives
    load(MUGS)["s3k"]["median_mm"]["mean"] += 1.0
    for page, figures in PAGES.items():
        bad = mismatches((ROOT / page).read_text(encoding="utf-8"), load, figures)
        assert len(bad) == 1 and f"should read {shown}" in bad[0], (page, bad)
