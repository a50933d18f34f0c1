"""The pretrained page's one-machine readings of the scenes (docs/results/accuracy/pretrained/README.md): the
scratch U-Net's three seeds trained on the machine that trained the encoder's, read as the committed JSON
they come from (the rules of ``helpers.figures``), and the page's "in every seed" sentences checked seed by
seed."""

from __future__ import annotations

from helpers.figures import Figures, Getter, at, loader, mismatches, mm, value_at
from helpers.paths import REPO as ROOT
from helpers.pretrained_files import PLUSH, PLUSH_HERE

PAGE = "docs/results/accuracy/pretrained/README.md"
PLUSH_POINTS = ("head", "tail", "front_left_paw", "front_right_paw", "body")


def _gaps(encoder: str, scratch: str, path: str) -> Getter:
    """Per seed, the encoder's value at ``path`` (e.g. ``s3k/median_mm``) less the scratch model's."""
    return lambda load: [value_at(load(encoder), f"{path}/per_seed/{i}")
                         - value_at(load(scratch), f"{path}/per_seed/{i}") for i in range(3)]


def _cpu_ratio(encoder: str, scratch: str, model: str) -> Getter:
    return lambda load: (load(encoder)[model]["train_cpu_minutes"]["mean"]
                         / load(scratch)[model]["train_cpu_minutes"]["mean"])


PLUSH_FIGURES: Figures = [
    ("scratch S3K {} mm median ({}, {}, {}), RMS {} mm, {} CPU-minutes per model; the encoder's S3K"
     " median is lower in every seed, by {} to {} mm, at {} times the CPU, and its RMS lower in two seeds"
     " and higher in the third ({} against {} mm).",
     [mm(PLUSH_HERE, "s3k/median_mm/mean")]
     + [mm(PLUSH_HERE, f"s3k/median_mm/per_seed/{i}") for i in range(3)]
     + [mm(PLUSH_HERE, "s3k/rms_mm/mean"), ("d1", at(PLUSH_HERE, "s3k/train_cpu_minutes/mean"))]
     + [("d2", lambda load: -max(_gaps(PLUSH, PLUSH_HERE, "s3k/median_mm")(load))),
        ("d2", lambda load: -min(_gaps(PLUSH, PLUSH_HERE, "s3k/median_mm")(load))),
        ("d1", _cpu_ratio(PLUSH, PLUSH_HERE, "s3k")),
        mm(PLUSH, "s3k/rms_mm/per_seed/2"), mm(PLUSH_HERE, "s3k/rms_mm/per_seed/2")]),
    ("Labels only with the encoder has a lower median in every seed ({} against {} mm) and a higher RMS in"
     " every seed ({} against {} mm).",
     [mm(f, "labels_only/median_mm/mean") for f in (PLUSH, PLUSH_HERE)]
     + [mm(f, "labels_only/rms_mm/mean") for f in (PLUSH, PLUSH_HERE)]),
    ("Per keypoint (medians over seeds, encoder against scratch here): head {} against {} mm, tail {}"
     " against {}, front left paw {} against {}, front right paw {} against {}, body {} against {}.",
     [("d1", at(f, f"s3k/median_mm_per_keypoint/{p}/mean"))
      for p in PLUSH_POINTS for f in (PLUSH, PLUSH_HERE)]),
]


def test_every_one_machine_scene_figure_equals_its_json():
    text = (ROOT / PAGE).read_text(encoding="utf-8")
    assert mismatches(text, loader(), PLUSH_FIGURES) == []


def test_the_plush_claims_of_every_seed_hold():
    load = loader()
    s3k = _gaps(PLUSH, PLUSH_HERE, "s3k/median_mm")(load)
    assert all(g < 0 for g in s3k)
    rms = _gaps(PLUSH, PLUSH_HERE, "s3k/rms_mm")(load)
    assert [g < 0 for g in rms] == [True, True, False]
    assert all(g < 0 for g in _gaps(PLUSH, PLUSH_HERE, "labels_only/median_mm")(load))
    assert all(g > 0 for g in _gaps(PLUSH, PLUSH_HERE, "labels_only/rms_mm")(load))
    page = " ".join((ROOT / PAGE).read_text(encoding="utf-8").split())
    assert "the encoder's S3K median is lower in every seed, by" in page
    assert "has a lower median in every seed" in page and "a higher RMS in every seed" in page
