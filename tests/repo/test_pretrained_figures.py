"""The tables of docs/results/accuracy/pretrained/README.md (the encoder against the scratch U-Net: the box's
label-curve points at 10, 5 and 20 labels, the real recording, the unseen mugs, the plush toy, cable
insertion) read as the committed JSON they come from, to the digits shown (the rules of
``helpers.figures``)."""

from __future__ import annotations

from helpers.figures import Figures, Getter, at, derived, loader, mismatches, mm, pct, value_at
from helpers.paths import REPO as ROOT
from helpers.pretrained_files import (
    CURVE,
    CURVE_5,
    CURVE_5_CONTROL,
    CURVE_5_POSES,
    CURVE_5_POSES_12,
    CURVE_20,
    CURVE_20_CONTROL,
    CURVE_20_POSES,
    CURVE_20_POSES_12,
    ENCODER_CURVES,
    INSERTION,
    INSERTION_CONTROL,
    INSERTION_HERE,
    INSERTION_POSES,
    INSERTION_SEED0_POSES,
    MUGS,
    PAGE,
    PLUSH,
    PLUSH_CONTROL,
    REAL,
    SCRATCH_CURVE,
    SCRATCH_HERE,
    SCRATCH_INSERTION,
    SCRATCH_MUGS,
    SCRATCH_PLUSH,
    cpu_ratio,
    page_words,
    real_row,
    seed_gaps,
    side_by_side_cpu_ratio,
)

MUG_POINTS = ("handle", "body_centre", "lip")


def _spread(file: str, path: str) -> list[tuple[str, Getter]]:
    """A mean over seeds, then each seed's value."""
    return [mm(file, f"{path}/mean")] + [mm(file, f"{path}/per_seed/{i}") for i in range(3)]


def _cpu_range(file: str, model: str) -> list[tuple[str, Getter]]:
    """The least and the most CPU-minutes over seeds, for files that list them per seed only."""
    return [("d1", derived(file, lambda d: min(d[model]["train_cpu_minutes"]["per_seed"]))),
            ("d1", derived(file, lambda d: max(d[model]["train_cpu_minutes"]["per_seed"])))]


def _curve_row(file: str, model: str, labels: int = 10) -> list[tuple[str, Getter]]:
    base = f"curve/{model}/{labels}"
    return (_spread(file, f"{base}/median_mm") + _spread(file, f"{base}/rms_mm")
            + [pct(file, f"{base}/pck_10mm/mean")]
            + [("d1", at(file, f"{base}/train_cpu_minutes/{k}")) for k in ("mean", "min", "max")])


def _mugs_row(file: str, model: str, cpu_range: bool) -> list[tuple[str, Getter]]:
    out = _spread(file, f"{model}/median_mm") + [mm(file, f"{model}/rms_mm/mean")]
    out += [pct(file, f"{model}/pck_10mm/mean")]
    out += [("d1", at(file, f"{model}/median_mm_per_keypoint/{k}/mean")) for k in MUG_POINTS]
    out.append(("d1", at(file, f"{model}/train_cpu_minutes/mean")))
    return out + (_cpu_range(file, model) if cpu_range else [])


def _scene_row(file: str, model: str, median_rule: str = "sig") -> list[tuple[str, Getter]]:
    """A scene's row: median and RMS (mean, per seed), share within 10 mm, CPU-minutes (mean, range); the
    medians rounded by ``median_rule`` (insertion's points are found to tenths of a mm: ``d3``)."""
    out = [(median_rule, get) for _, get in _spread(file, f"{model}/median_mm")]
    out += _spread(file, f"{model}/rms_mm")
    out += [pct(file, f"{model}/pck_10mm/mean"), ("d1", at(file, f"{model}/train_cpu_minutes/mean"))]
    return out + _cpu_range(file, model)


def _paired(path: str, pick, encoder: str = PLUSH, scratch: str = SCRATCH_PLUSH) -> Getter:
    """``pick`` (min or max) over seeds 0-2 of the encoder's figure at ``path`` (e.g. ``s3k/median_mm``) less
    the scratch model's (the plush's unless named)."""
    return lambda load: pick(seed_gaps(encoder, scratch, path)(load))


def _run(file: str, index: int) -> Getter:
    """The ``index``-th run (in the order given) of a by-pose file."""
    return lambda load: list(load(file)["runs"].values())[index]


def _pose_group(file: str, index: int, pose: str, fn) -> Getter:
    """``fn`` of ``pose``'s group of the ``index``-th run of a by-pose file."""
    return lambda load: fn(_run(file, index)(load)["by_pose"][pose])


def _pose_run(seed: int, key: str) -> Getter:
    """``key`` (keys joined by ``/``) of the insertion S3K model of ``seed`` (1 or 2) in the by-pose file."""
    return lambda load: value_at(_run(INSERTION_POSES, seed - 1)(load), key)


def _control_gap(encoder: str, path: str, control: str, key: str = "median_mm") -> Getter:
    """Seed 0's encoder model (``path``: its model in ``encoder``, e.g. ``s3k``) less the same-machine scratch
    control of that seed, in ``key``."""
    return lambda load: (value_at(load(encoder), f"{path}/{key}/per_seed/0")
                         - load(control)["metrics"][key])


def _control_cpu_ratio(encoder: str, path: str, control: str) -> Getter:
    """Seed 0's encoder model's CPU-minutes over the same-machine scratch control's."""
    return lambda load: (value_at(load(encoder), f"{path}/train_cpu_minutes/per_seed/0")
                         / load(control)["cpu_minutes"])


def _below_control(key: str) -> Getter:
    """The same-machine scratch model of seed 0 less the encoder's model of seed 0, on the plush."""
    return lambda load: -_control_gap(PLUSH, "s3k", PLUSH_CONTROL, key)(load)


def _keypoint(file: str, point: str) -> tuple[str, Getter]:
    return "d1", at(file, f"s3k/median_mm_per_keypoint/{point}/mean")


CURVE_ROW = "| {} ({}, {}, {}) | {} ({}, {}, {}) | {}% | {} ({}-{})"


def _table(rms_header: str, row: str) -> str:
    """A four-row table of the encoder against scratch, S3K then labels only; the scratch rows' CPU figures
    are the Xeon's."""
    head = (f"| model | median mm (seeds 0, 1, 2) {rms_header} within 10 mm | CPU-minutes |\n"
            "|---|---|---|---|---|\n")
    rows = [f"| {m}, {e} {row}{' |' if e == 'encoder' else ', the Xeon |'}"
            for m in ("S3K", "labels only") for e in ("encoder", "scratch")]
    return head + "\n".join(rows)


def _seed0_side(run: int, fn) -> Getter:
    """``fn`` of the "on a side" group (insertion's only pose) of seed 0's model ``run`` (0: the encoder's, 1:
    the scratch control) in ``insertion-by-pose-seed0.json``."""
    return _pose_group(INSERTION_SEED0_POSES, run, "on a side", fn)


def _tip_lean(side: dict) -> float:
    return float(sum(x * x for x in side["bias_mm"][0]) ** 0.5)


def _share(seed: int, frames: str) -> tuple[str, Getter]:
    """The percentage of the squared error carried by the ``frames`` (swapped, collapsed) of ``seed``."""
    return "d0", lambda load: 100 * _pose_run(seed, f"{frames}/share_of_squared_error")(load)


def _after_link(scene: str) -> str:
    """The end of the sentence that introduces a scene's table (the two scenes' tables read alike)."""
    return f"(../headline-preset/{scene}/summary.json), the same seeds, trained on the Intel Xeon):\n\n"


MUGS_ROW = "| {} ({}, {}, {}) | {} | {}% | {} / {} / {} | {}"

FIGURES: Figures = [
    (_table("| RMS mm |", CURVE_ROW),
     _curve_row(CURVE, "s3k") + _curve_row(SCRATCH_CURVE, "s3k") + _curve_row(CURVE, "labels_only")
     + _curve_row(SCRATCH_CURVE, "labels_only")),
    *[(f"| {seed} | {{}} ({{}}) | {{}} ({{}}) | {{}} [{{}}, {{}}] | {{}} against {{}} |",
       real_row(REAL, seed)) for seed in range(3)],
    ("Over seeds: {} mm, 95% t-interval {} to {};",
     [("d3", at(REAL, "mean_paired_diff_mm"))]
     + [("d3", at(REAL, f"mean_paired_diff_ci95_mm_over_seeds/{i}")) for i in range(2)]),
    ("| S3K, encoder " + MUGS_ROW + " ({}-{}) |", _mugs_row(MUGS, "s3k", True)),
    ("| S3K, scratch " + MUGS_ROW + ", the Xeon |", _mugs_row(SCRATCH_MUGS, "s3k", False)),
    ("| labels only, encoder " + MUGS_ROW + " ({}-{}) |", _mugs_row(MUGS, "labels_only", True)),
    ("| labels only, scratch " + MUGS_ROW + ", the Xeon |", _mugs_row(SCRATCH_MUGS, "labels_only", False)),
    (_after_link("plush") + _table("| RMS mm (seeds 0, 1, 2) |", CURVE_ROW),
     _scene_row(PLUSH, "s3k") + _scene_row(SCRATCH_PLUSH, "s3k") + _scene_row(PLUSH, "labels_only")
     + _scene_row(SCRATCH_PLUSH, "labels_only")),
    ("S3K's is lower in every seed, by {} to {} mm.",
     [("d2", lambda load: -_paired("s3k/median_mm", max)(load)),
      ("d2", lambda load: -_paired("s3k/median_mm", min)(load))]),
    ("higher in the third ({} mm against {}), where the front right paw keeps a tail of errors (RMS {}",
     [mm(PLUSH, "s3k/rms_mm/per_seed/2"), mm(SCRATCH_PLUSH, "s3k/rms_mm/per_seed/2"),
      ("sig", at(PLUSH, "s3k/rms_mm_per_keypoint/front_right_paw/per_seed/2"))]),
    ("gives {} mm median, {} mm RMS, in {} CPU-minutes: the encoder's model of that seed is {} mm lower in"
     " median and {} mm in RMS",
     [mm(PLUSH_CONTROL, "metrics/median_mm"), mm(PLUSH_CONTROL, "metrics/rms_mm"),
      ("d1", at(PLUSH_CONTROL, "cpu_minutes")),
      ("d2", _below_control("median_mm")), ("d2", _below_control("rms_mm"))]),
    ("scratch): head {} against {} mm, tail {} against {}, front left paw {} against {}, front right paw {}"
     " against {}, body {} against {}.",
     [_keypoint(f, p) for p in ("head", "tail", "front_left_paw", "front_right_paw", "body")
      for f in (PLUSH, SCRATCH_PLUSH)]),
]


def _box_pose(file: str, run: int, pose: str, fn) -> tuple[str, Getter]:
    """``fn`` of ``pose``'s group of seed 0's box model ``run`` (0: the encoder's, 1: the scratch control) in
    the by-pose ``file``, to tenths (the leans) or hundredths (the medians without them)."""
    return "d1" if fn is _normal_lean else "d2", _pose_group(file, run, pose, fn)


def _normal_lean(group: dict) -> float:
    """The three corners' mean error along the face's normal (the by-pose frame's z)."""
    return sum(b[2] for b in group["bias_mm"]) / len(group["bias_mm"])


def _without_lean(group: dict) -> float:
    return group["median_mm_without_bias"]


POSES = ("normal up", "normal down", "on a side")

FIVE_LABEL_FIGURES: Figures = [
    ("(../label-curve/summary.json), trained on the Intel Xeon):\n\n"
     + _table("| RMS mm (seeds 0, 1, 2) |", CURVE_ROW),
     _curve_row(CURVE_5, "s3k", 5) + _curve_row(SCRATCH_CURVE, "s3k", 5)
     + _curve_row(CURVE_5, "labels_only", 5) + _curve_row(SCRATCH_CURVE, "labels_only", 5)),
    ("S3K's median is higher with the encoder in every seed, by {} to {} mm.",
     [("d2", _paired("curve/s3k/5/median_mm", pick, CURVE_5, SCRATCH_CURVE)) for pick in (min, max)]),
    ("(seed 2's tail is {} mm against\n{})",
     [mm(CURVE_5, "curve/s3k/5/rms_mm/per_seed/2"), mm(SCRATCH_CURVE, "curve/s3k/5/rms_mm/per_seed/2")]),
    ("(`label-curve-5-scratch-seed0.json`) gives {} mm median, {} mm RMS, in {}\nCPU-minutes: the encoder's"
     " model of that seed is {} mm higher in"
     " median, at {} times the CPU.",
     [mm(CURVE_5_CONTROL, "metrics/median_mm"), mm(CURVE_5_CONTROL, "metrics/rms_mm"),
      ("d1", at(CURVE_5_CONTROL, "cpu_minutes")),
      ("d2", _control_gap(CURVE_5, "curve/s3k/5", CURVE_5_CONTROL)),
      ("d1", _control_cpu_ratio(CURVE_5, "curve/s3k/5", CURVE_5_CONTROL))]),
    ("flat with the marked face up {} mm against {}, face down {} against {}, on a side {} against {}",
     [_box_pose(CURVE_5_POSES, r, pose, _without_lean) for pose in POSES for r in (0, 1)]),
    ("{} mm with the encoder against {} face up, {} against {} face down, {} against {} on a side.",
     [_box_pose(CURVE_5_POSES, r, pose, _normal_lean) for pose in POSES for r in (0, 1)]),
]


def _seed0(file: str, model: str, key: str, count: int = 20) -> Getter:
    return at(file, f"curve/{model}/{count}/{key}/per_seed/0")


def _swapped_share(run: int) -> tuple[str, Getter]:
    return "d0", lambda load: 100 * _run(CURVE_20_POSES, run)(load)["swapped"]["share_of_squared_error"]


TWENTY_LABEL_FIGURES: Figures = [
    ("[../label-curve](../label-curve/summary.json)):\n\n" + _table("| RMS mm (seeds 0, 1, 2) |", CURVE_ROW),
     _curve_row(CURVE_20, "s3k", 20) + _curve_row(SCRATCH_CURVE, "s3k", 20)
     + _curve_row(CURVE_20, "labels_only", 20) + _curve_row(SCRATCH_CURVE, "labels_only", 20)),
    ("S3K's is higher in every seed, by {} to\n{} mm",
     [("d2", _paired("curve/s3k/20/median_mm", pick, CURVE_20, SCRATCH_CURVE)) for pick in (min, max)]),
    ("(`label-curve-20-scratch-seed0.json`): {} mm median, {} mm RMS,\n{} CPU-minutes; the committed scratch"
     " model of seed 0, trained on the Xeon, {} mm and {} mm, so the same options on another CPU move this"
     " point by about {} mm of median.",
     [mm(CURVE_20_CONTROL, "metrics/median_mm"), mm(CURVE_20_CONTROL, "metrics/rms_mm"),
      ("d1", at(CURVE_20_CONTROL, "cpu_minutes")),
      ("sig", _seed0(SCRATCH_CURVE, "s3k", "median_mm")), ("sig", _seed0(SCRATCH_CURVE, "s3k", "rms_mm")),
      ("d1", lambda load: load(CURVE_20_CONTROL)["metrics"]["median_mm"]
       - _seed0(SCRATCH_CURVE, "s3k", "median_mm")(load))]),
    ("(face up {} mm against {}, face down\n{} against {}, on a side {} against {})",
     [_box_pose(CURVE_20_POSES, r, pose, _without_lean) for pose in POSES for r in (0, 1)]),
    ("(face up {} mm against {}, on a side {} against {})",
     [_box_pose(CURVE_20_POSES, r, pose, _normal_lean) for pose in ("normal up", "on a side")
      for r in (0, 1)]),
    ("({}% and {}% of the squared error)", [_swapped_share(0), _swapped_share(1)]),
]


def _seed_pairs(load, count: int, model: str, key: str, scratch: str = SCRATCH_CURVE
                ) -> list[tuple[float, float]]:
    """Per seed, the encoder's ``key`` of ``model`` at ``count`` labels beside the scratch curve's (the
    committed one, trained on the Xeon, unless named)."""
    return list(zip(*(load(f)["curve"][model][str(count)][key]["per_seed"]
                      for f in (ENCODER_CURVES[count], scratch))))


def test_the_twenty_label_claims_of_every_seed_hold():
    """The 20-label section's "in every seed" sentences, from the JSON."""
    load = loader()
    assert all(enc > scratch for enc, scratch in _seed_pairs(load, 20, "s3k", "median_mm"))
    assert all(enc > scratch for enc, scratch in _seed_pairs(load, 20, "labels_only", "median_mm"))
    assert all(enc < scratch for enc, scratch in _seed_pairs(load, 20, "s3k", "pck_10mm"))
    page = page_words()
    for claim in ("S3K's is higher in every seed, by", "and so is labels only's;",
                  "S3K's share within 10 mm is lower in every seed"):
        assert claim in page


def _same_machine_row(n: int) -> list[tuple[str, Getter]]:
    """A row of the one-machine table: S3K's median (mean, per seed) with the encoder and from scratch, then
    RMS, share within 10 mm and CPU-minutes, encoder / scratch."""
    files = (ENCODER_CURVES[n], SCRATCH_HERE)
    base = f"curve/s3k/{n}"
    out = [cell for f in files for cell in _spread(f, f"{base}/median_mm")]
    out += [mm(f, f"{base}/rms_mm/mean") for f in files] + [pct(f, f"{base}/pck_10mm/mean") for f in files]
    return out + [("d1", at(f, f"{base}/train_cpu_minutes/mean")) for f in files]


def _gaps_here(load, model: str, key: str = "median_mm") -> list[list[float]]:
    """Per label count (5, 10, 20), per seed: the encoder's ``key`` less the scratch model's trained here."""
    return [[a - b for a, b in _seed_pairs(load, n, model, key, SCRATCH_HERE)] for n in (5, 10, 20)]


def _lean_gaps(load) -> list[float]:
    """In every pose of every seed at 5 and 20 labels, the encoder's lean along the face's normal less the
    scratch model's (negative: the encoder's is longer, into the box)."""
    out = []
    for file, pairs in ((CURVE_5_POSES, [(0, 1)]), (CURVE_20_POSES, [(0, 1)]),
                        (CURVE_5_POSES_12, [(0, 1), (2, 3)]), (CURVE_20_POSES_12, [(0, 1), (2, 3)])):
        for enc, scratch in pairs:
            runs = [_run(file, i)(load)["by_pose"] for i in (enc, scratch)]
            out += [_normal_lean(runs[0][p]) - _normal_lean(runs[1][p]) for p in POSES]
    return out


def _scratch_spread(load) -> float:
    """The largest difference of a scratch S3K median (any count and seed) between this machine and the
    Xeon."""
    return max(abs(a - b) for n in ("5", "10", "20") for a, b in zip(
        *(load(f)["curve"]["s3k"][n]["median_mm"]["per_seed"] for f in (SCRATCH_HERE, SCRATCH_CURVE))))


SAME_MACHINE_FIGURES: Figures = [
    *[(f"| {n} | {{}} ({{}}, {{}}, {{}}) | {{}} ({{}}, {{}}, {{}}) | {{}} / {{}} | {{}}% / {{}}% |"
       " {} / {} |", _same_machine_row(n)) for n in (5, 10, 20)],
    ("S3K's median is higher with the encoder in every seed at every count, by {}\nto {} mm.",
     [("d2", lambda load: min(min(g) for g in _gaps_here(load, "s3k"))),
      ("d2", lambda load: max(max(g) for g in _gaps_here(load, "s3k")))]),
    ("(seed 2: {} mm on the Xeon, {} here)",
     [mm(SCRATCH_CURVE, "curve/s3k/5/rms_mm/per_seed/2"), mm(SCRATCH_HERE, "curve/s3k/5/rms_mm/per_seed/2")]),
    ("It costs {} times the CPU of a\nscratch model at 5 and 20 labels for S3K, {} for labels only",
     [("d1", lambda load: side_by_side_cpu_ratio(load, "s3k")),
      ("d1", lambda load: side_by_side_cpu_ratio(load, "labels_only"))]),
    ("differ by up to {} mm (seed 2 at five labels)", [("d2", _scratch_spread)]),
    ("is longer with the encoder, by {} to {} mm.",
     [("d2", lambda load: -max(_lean_gaps(load))), ("d2", lambda load: -min(_lean_gaps(load)))]),
]


def test_the_one_machine_claims_of_every_seed_hold():
    """The one-machine section's "in every seed" and "in every pose" sentences, from the JSON."""
    load = loader()
    s3k = _gaps_here(load, "s3k")
    assert all(g > 0 for per_count in s3k for g in per_count)
    assert all(g > 0 for g in _gaps_here(load, "s3k", "pck_10mm")[0])
    labels_only = _gaps_here(load, "labels_only")
    assert sorted(g < 0 for g in labels_only[0]) == [False, True, True] and all(g > 0 for g in labels_only[2])
    leans = _lean_gaps(load)
    assert all(g < 0 for g in leans) and len(leans) == 18
    spread = [abs(a - b) for a, b in zip(*(load(f)["curve"]["s3k"]["5"]["median_mm"]["per_seed"]
                                          for f in (SCRATCH_HERE, SCRATCH_CURVE)))]
    assert max(spread) == _scratch_spread(load) == spread[2]
    page = page_words()
    for claim in ("higher with the encoder in every seed at every count",
                  "a higher share within 10 mm, in every seed",
                  "lower at five labels in two seeds of three and higher at twenty in every seed",
                  "In every pose of every seed, at five labels and at twenty"):
        assert claim in page


INSERTION_FIGURES: Figures = [
    (_after_link("insertion") + _table("| RMS mm (seeds 0, 1, 2) |", CURVE_ROW),
     [cell for file, model in ((INSERTION, "s3k"), (SCRATCH_INSERTION, "s3k"), (INSERTION, "labels_only"),
                               (SCRATCH_INSERTION, "labels_only"))
      for cell in _scene_row(file, model, "d3")]),
    ("S3K's median is higher in every seed, by {} to {} mm",
     [("d3", _paired("s3k/median_mm", pick, INSERTION, SCRATCH_INSERTION)) for pick in (min, max)]),
    ("in seed 1, {} frames where keypoints swap carry {}% of the squared error and {} collapsed frame {}%; in"
     " seed 2, {} collapsed frames carry {}%. Without those frames the RMS is {} and {} mm",
     [("d0", _pose_run(1, "swapped_frames")), _share(1, "swapped"),
      ("d0", _pose_run(1, "collapsed_frames")), _share(1, "collapsed"),
      ("d0", _pose_run(2, "collapsed_frames")), _share(2, "collapsed"),
      ("sig", _pose_run(1, "neither/rms_mm")), ("sig", _pose_run(2, "neither/rms_mm"))]),
    ("(`insertion-scratch-seed0.json`) gives {} mm median,\n{} mm RMS, in {} CPU-minutes: the encoder's model"
     " of that seed is {} mm higher in"
     " median, at {} times the\nCPU",
     [("d3", at(INSERTION_CONTROL, "metrics/median_mm")), mm(INSERTION_CONTROL, "metrics/rms_mm"),
      ("d1", at(INSERTION_CONTROL, "cpu_minutes")),
      ("d3", _control_gap(INSERTION, "s3k", INSERTION_CONTROL)),
      ("d1", _control_cpu_ratio(INSERTION, "s3k", INSERTION_CONTROL))]),
    ("the plug tip's lean, the length of its mean error, is {} mm with the encoder\nagainst {}, and with each"
     " keypoint's lean taken away the medians are {} and {} mm.",
     [("d2", _seed0_side(0, _tip_lean)), ("d2", _seed0_side(1, _tip_lean)),
      ("d3", _seed0_side(0, lambda s: s["median_mm_without_bias"])),
      ("d3", _seed0_side(1, lambda s: s["median_mm_without_bias"]))]),
    ("scratch S3K {} mm median ({}, {}, {}), RMS {} mm, {}\nCPU-minutes per model; the encoder's S3K median"
     " is higher in every seed, by {} to {} mm, at {} times the\nCPU, and its labels-only median is lower in"
     " every seed ({} against {} mm)",
     [("d3", get) for _, get in _spread(INSERTION_HERE, "s3k/median_mm")]
     + [mm(INSERTION_HERE, "s3k/rms_mm/mean"), ("d1", at(INSERTION_HERE, "s3k/train_cpu_minutes/mean"))]
     + [("d3", _paired("s3k/median_mm", pick, INSERTION, INSERTION_HERE)) for pick in (min, max)]
     + [("d1", cpu_ratio(INSERTION, INSERTION_HERE, "s3k"))]
     + [("d3", at(f, "labels_only/median_mm/mean")) for f in (INSERTION, INSERTION_HERE)]),
    ("plug tip {} against {} mm, plug base\n{} against {}, socket {} against {}.",
     [("d3", at(f, f"s3k/median_mm_per_keypoint/{p}/mean")) for p in ("plug_tip", "plug_base", "socket")
      for f in (INSERTION, SCRATCH_INSERTION)]),
]


def test_every_pretrained_figure_equals_its_json():
    text = (ROOT / PAGE).read_text(encoding="utf-8")
    box = FIVE_LABEL_FIGURES + TWENTY_LABEL_FIGURES + SAME_MACHINE_FIGURES
    assert mismatches(text, loader(), FIGURES + box + INSERTION_FIGURES) == []


def test_a_changed_pretrained_json_value_fails():
    text = (ROOT / PAGE).read_text(encoding="utf-8")
    load = loader()
    load(MUGS)["s3k"]["median_mm_per_keypoint"]["body_centre"]["mean"] = 11.0
    bad = mismatches(text, load, FIGURES)
    assert len(bad) == 1 and "should read 11.0" in bad[0]


def test_labels_only_with_the_encoder_is_lower_on_insertion_in_every_seed_as_the_page_says():
    """Against both scratch summaries (the Xeon's, this machine's); and S3K's median is higher in every seed
    against the one trained here."""
    load = loader()
    for scratch_file in (SCRATCH_INSERTION, INSERTION_HERE):
        enc, scratch = (load(f)["labels_only"]["median_mm"]["per_seed"] for f in (INSERTION, scratch_file))
        assert all(a < b for a, b in zip(enc, scratch))
    enc, scratch = (load(f)["s3k"]["median_mm"]["per_seed"] for f in (INSERTION, INSERTION_HERE))
    assert all(a > b for a, b in zip(enc, scratch))
    page = page_words()
    assert "Labels only with the encoder has a lower median than from scratch in every seed" in page


def test_the_five_label_claims_of_every_seed_and_pose_hold():
    """The sentences of the 5-label section that say "in every seed" or "in every pose", from the JSON."""
    load = loader()
    assert all(enc > scratch for enc, scratch in _seed_pairs(load, 5, "s3k", "median_mm"))
    assert all(enc > scratch for enc, scratch in _seed_pairs(load, 5, "s3k", "pck_10mm"))
    assert all(enc < scratch for enc, scratch in _seed_pairs(load, 5, "labels_only", "median_mm"))
    runs = [_run(CURVE_5_POSES, i)(load) for i in (0, 1)]
    assert all(_without_lean(runs[0]["by_pose"][p]) < _without_lean(runs[1]["by_pose"][p]) for p in POSES)
    assert all(_normal_lean(runs[0]["by_pose"][p]) < _normal_lean(runs[1]["by_pose"][p]) for p in POSES)
    page = page_words()
    for claim in ("S3K's median is higher with the encoder in every seed",
                  "share within 10 mm is higher in every seed", "labels only's median is lower in every seed",
                  "the medians are lower with the encoder in every pose", "leans as far or further"):
        assert claim in page
