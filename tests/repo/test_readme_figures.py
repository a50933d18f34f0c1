"""Every figure in README.md's results (the Results table and its bullets, the label curve, cameras outside
the rig, the Speed table, the demo) equals the value in the committed JSON it comes from, to the digits shown.

Each entry of ``FIGURES`` is a piece of the README with ``{}`` where a figure stands, and for each ``{}`` the
JSON value and its rounding rule (``helpers.figures``). The piece must occur exactly once in the README (a
reworded sentence fails here until its entry is updated) and each figure must read exactly as its JSON value
rounded by the rule: a README figure edited by hand, or a JSON file measured again, fails the test.
"""

from __future__ import annotations

from collections.abc import Callable
from statistics import mean

import pytest
from helpers import pretrained_files as pretrained
from helpers.figures import (
    Figures,
    Getter,
    at,
    derived,
    loader,
    mismatches,
    mm,
    pct,
    seeds_mean,
    sig,
    value_at,
)
from helpers.paths import REPO as ROOT


def row(file: str, model: str) -> list[tuple[str, Getter]]:
    """A Results-table row: median (per seed), RMS (per seed), share within 10 mm, mean CPU-minutes."""
    out = [mm(file, f"{model}/median_mm/mean")]
    out += [mm(file, f"{model}/median_mm/per_seed/{i}") for i in range(3)]
    out += [mm(file, f"{model}/rms_mm/mean")]
    out += [mm(file, f"{model}/rms_mm/per_seed/{i}") for i in range(3)]
    out += [pct(file, f"{model}/pck_10mm/mean"), ("d1", at(file, f"{model}/train_cpu_minutes/mean"))]
    return out


ROW = "| {} mm ({}, {}, {}) | {} mm ({}, {}, {}) | {}% | {} CPU-min |"
BOLD_ROW = "| **{} mm ({}, {}, {})** | **{} mm ({}, {}, {})** | **{}%** |"

BOX = "docs/results/accuracy/summary.json"
FAST = "docs/results/accuracy/fast/box-fast/summary.json"
FIVE = "docs/results/accuracy/five-seeds/summary.json"
PLUSH = "docs/results/accuracy/headline-preset/plush/summary.json"
MUGS = "docs/results/accuracy/headline-preset/category/summary.json"
INSERTION = "docs/results/accuracy/headline-preset/insertion/summary.json"
DISTRACTORS = "docs/results/accuracy/distractors/summary.json"
REAL = "docs/results/real/headline-preset/comparison.json"
REAL_ONE_PASS = "docs/results/real/comparison.json"
REAL_HELD_OUT = "docs/results/real/held-out/comparison.json"
AUTO_CROPS = "docs/results/real/held-out/auto-crops.json"
REAL_END = "docs/results/real/held-out-end/comparison.json"
REAL_PRETRAINED, PLUSH_PRETRAINED, MUGS_PRETRAINED = pretrained.REAL, pretrained.PLUSH, pretrained.MUGS
REAL_PRETRAINED_LABELS_ONLY = pretrained.REAL_LABELS_ONLY
REAL_END_ADAPT = "docs/results/real/held-out-end/adaptation.json"
CURVE = "docs/results/accuracy/label-curve/summary.json"
ENCODER = "added_curves/efficientnet-lite0/"  # the encoder's points within CURVE
PLUSH_CURVE = "docs/results/accuracy/label-curve/plush/summary.json"
DIAGNOSIS = "docs/results/accuracy/outside-rig/s3k-seed0-diagnosis.json"
SPEED = "docs/results/accuracy/fast/summary.json"
QUIET = "docs/results/benchmarks/inference-cpu-batch1-quiet.json"
ONE_PASS = "docs/results/benchmarks/inference-cpu-batch1.json"
DEMO = "docs/results/demo/box-fast-comparison.json"
ROBOT = "docs/results/robot/summary.json"
WIDE = "docs/results/accuracy/outside-rig/wide-rig-el10-70-seeds.json"


def _curve(model: str, key: str, pick: Callable) -> Callable[[dict], float]:
    """``pick`` (min or max) over the label counts of each count's mean over seeds."""
    return lambda d: pick(v[key]["mean"] for v in d["curve"][model].values())


def _ratios(rig: str, sets: tuple[str, ...], pick: Callable) -> Getter:
    """``pick`` (min or max) of the per-seed ratios to the in-range median of ``sets`` on ``rig``."""
    return derived(WIDE, lambda d: pick(r for s in sets for r in d["outside_rigs"][rig][s]["ratio_per_seed"]))


def _real_rows(file: str = REAL_HELD_OUT, models: tuple[str, ...] = ("baseline", "s3k")
               ) -> list[tuple[str, Getter]]:
    out = []
    for model in models:
        for key in ("median_mm", "mean_mm", "rms_mm"):
            out.append(("sig", derived(file, seeds_mean(model, key))))
            if key != "mean_mm":
                out += [mm(file, f"seeds/{i}/{model}/{key}") for i in range(3)]
        out.append(("d1", derived(file, seeds_mean(model, "cpu_minutes"))))
    return out


FIGURES: Figures = [
    # The demo, quick start.
    ("it takes {} minutes, set-up included, and prints S3K {} mm median and {} mm RMS against labels only's"
     " {} and {} mm ([box-fast-comparison.json](docs/results/demo/box-fast-comparison.json))",
     [("d1", at(DEMO, "wall_minutes_with_setup")), mm(DEMO, "S3K/median_mm"), mm(DEMO, "S3K/rms_mm"),
      mm(DEMO, "labels only/median_mm"), mm(DEMO, "labels only/rms_mm")]),
    # The pretrained encoder's points in the label curve.
    ("[pretrained](docs/results/accuracy/pretrained/README.md)): S3K {}, {} and {} mm median, higher than"
     " from scratch in every seed, on this figure and beside scratch models trained on the same machine"
     " ([scratch-curve](docs/results/accuracy/pretrained/scratch-curve/summary.json)), where it takes {}"
     " times the CPU. Its RMS is level with those at 5 labels ({} mm against {}; the figure's scratch seeds"
     " give {}) and higher at 10 and 20 ({} against {}, {} against {})",
     [mm(CURVE, f"{ENCODER}curve/s3k/{n}/median_mm/mean") for n in (5, 10, 20)]
     + [("d1", lambda load: pretrained.side_by_side_cpu_ratio(load, "s3k"))]
     + [mm(f, "curve/s3k/5/rms_mm/mean") for f in (pretrained.CURVE_5, pretrained.SCRATCH_HERE, CURVE)]
     + [mm(f, f"curve/s3k/{n}/rms_mm/mean") for n in (10, 20)
        for f in (pretrained.ENCODER_CURVES[n], pretrained.SCRATCH_HERE)]),
    # The Results table.
    (f"([summary]({BOX})) | labels only {ROW}\n| | **S3K** {BOLD_ROW} **{{}} CPU-min** |",
     row(BOX, "labels_only") + row(BOX, "s3k")),
    (f"([summary]({FAST})) | labels only {ROW}\n| | S3K {ROW}", row(FAST, "labels_only") + row(FAST, "s3k")),
    (f"([summary]({PLUSH}); earlier options: [accuracy.md](docs/accuracy.md"
     f"#the-headline-preset-on-other-scenes)) | labels only {ROW}\n| | **S3K** {BOLD_ROW} {{}} CPU-min |",
     row(PLUSH, "labels_only") + row(PLUSH, "s3k")),
    (f"[plush.json]({PLUSH_PRETRAINED})) {ROW}", row(PLUSH_PRETRAINED, "s3k")),
    (f"([summary]({MUGS})) | labels only {ROW}\n| | S3K {ROW}", row(MUGS, "labels_only") + row(MUGS, "s3k")),
    (f"([summary]({INSERTION})) | labels only {ROW}\n| | **S3K** {BOLD_ROW} {{}} CPU-min |",
     row(INSERTION, "labels_only") + row(INSERTION, "s3k")),
    ("`+modified`) | labels only | {} mm | {} mm | {}% | |\n| | S3K | {} mm | {} mm | {}% | |",
     [spec for m in ("labels_only", "s3k") for spec in
      (mm(DISTRACTORS, f"{m}/median_mm/mean"), mm(DISTRACTORS, f"{m}/rms_mm/mean"),
       pct(DISTRACTORS, f"{m}/pck_10mm/mean"))]),
    ("S3K {}, labels only {} mm mean ([comparison](docs/results/real/headline-preset/comparison.json))",
     [("sig", derived(REAL, seeds_mean(m, "mean_mm"))) for m in ("s3k", "baseline")]),
    ("5 seeds: S3K {}, labels only {} mm median, [comparison](docs/results/real/comparison.json))",
     [("sig", derived(REAL_ONE_PASS, seeds_mean(m, "median_mm"))) for m in ("s3k", "baseline")]),
    ("| labels only | {} mm ({}, {}, {}); mean {} | {} mm ({}, {}, {}) | | {} CPU-min |\n"
     "| | S3K | {} mm ({}, {}, {}); mean {} | {} mm ({}, {}, {}) | | {} CPU-min |", _real_rows()),
    (f"encoder, [real-held-out.json]({REAL_PRETRAINED})) | {{}} mm ({{}}, {{}}, {{}}); mean {{}} "
     "| {} mm ({}, {}, {}) | | {} CPU-min |", _real_rows(REAL_PRETRAINED, ("pretrained",))),
    (f"[real-held-out-labels-only.json]({REAL_PRETRAINED_LABELS_ONLY})) | {{}} mm ({{}}, {{}}, {{}}); mean"
     " {} | {} mm ({}, {}, {}) | | {} CPU-min |", _real_rows(REAL_PRETRAINED_LABELS_ONLY, ("pretrained",))),
    ("with it, labels only lies as near ({} mm mean against S3K's {}).",
     [("sig", derived(REAL_PRETRAINED_LABELS_ONLY, seeds_mean("pretrained", "mean_mm"))),
      ("sig", derived(REAL_PRETRAINED, seeds_mean("pretrained", "mean_mm")))]),
    ("lies nearer still in every seed: {} mm of mean, 95% interval {} to {},",
     [("signed", at(REAL_PRETRAINED, "mean_paired_diff_mm")),
      ("signed", at(REAL_PRETRAINED, "mean_paired_diff_ci95_mm_over_seeds/0")),
      ("signed", at(REAL_PRETRAINED, "mean_paired_diff_ci95_mm_over_seeds/1"))]),
    # The bullets under it.
    ("in {}-{} CPU-minutes per model",
     [("d1", derived(BOX, lambda d, f=f: f(d["s3k"]["train_cpu_minutes"]["per_seed"]))) for f in (min, max)]),
    ("labels only leaves {}% of the keypoints more than 10 mm off",
     [("d0", derived(BOX, lambda d: 100 * (1 - d["labels_only"]["pck_10mm"]["mean"])))]),
    ("Five seeds: {} / {} mm", [mm(FIVE, "s3k/median_mm/mean"), mm(FIVE, "s3k/rms_mm/mean")]),
    ("CPU time for a {} mm median", [mm(FAST, "s3k/median_mm/mean")]),
    ("on RMS in every seed ({}x) and on median in two of three (seed 1: {} against {} mm)",
     [("d2", derived(PLUSH, lambda d: d["s3k"]["rms_mm"]["mean"] / d["labels_only"]["rms_mm"]["mean"])),
      mm(PLUSH, "s3k/median_mm/per_seed/1"), mm(PLUSH, "labels_only/median_mm/per_seed/1")]),
    ("(one seed keeps a tail on a paw): {} mm against {} for scratch models of the same seeds trained on the"
     " same machine, in {} CPU-minutes against {}; on the mugs it is worse in every seed, {} mm median"
     " against {}, and on insertion slightly worse in every seed, {} mm against {}, both on the same machine",
     [mm(PLUSH_PRETRAINED, "s3k/median_mm/mean"), mm(pretrained.PLUSH_HERE, "s3k/median_mm/mean"),
      ("d1", at(PLUSH_PRETRAINED, "s3k/train_cpu_minutes/mean")),
      ("d1", at(pretrained.PLUSH_HERE, "s3k/train_cpu_minutes/mean")),
      mm(MUGS_PRETRAINED, "s3k/median_mm/mean"), mm(pretrained.MUGS_HERE, "s3k/median_mm/mean"),
      ("d3", at(pretrained.INSERTION, "s3k/median_mm/mean")),
      ("d3", at(pretrained.INSERTION_HERE, "s3k/median_mm/mean"))]),
    ("S3K is closer to them than labels only in every seed: paired difference {} mm of mean over three seeds,"
     " 95% interval {} to {}.",
     [("signed", at(REAL_HELD_OUT, "mean_paired_diff_mm")),
      ("signed", at(REAL_HELD_OUT, "mean_paired_diff_ci95_mm_over_seeds/0")),
      ("signed", at(REAL_HELD_OUT, "mean_paired_diff_ci95_mm_over_seeds/1"))]),
    ("it was level ({} mm, {} to {}; with one pass {} mm over five, {} to {})",
     [("signed", at(REAL, "mean_paired_diff_mm")),
      ("signed", at(REAL, "mean_paired_diff_ci95_mm_over_seeds/0")),
      ("signed", at(REAL, "mean_paired_diff_ci95_mm_over_seeds/1")),
      ("signed", at(REAL_ONE_PASS, "mean_paired_diff_mm")),
      ("signed", at(REAL_ONE_PASS, "mean_paired_diff_ci95_mm_over_seeds/0")),
      ("signed", at(REAL_ONE_PASS, "mean_paired_diff_ci95_mm_over_seeds/1"))]),
    ("than one pass on 128 px crops (median {} mm against {}-{})",
     [("sig", derived(REAL, lambda d: mean(mean(s[m]["median_mm"] for m in ("s3k", "baseline"))
                                           for s in d["seeds"].values()))),
      ("sig", derived(REAL_ONE_PASS, seeds_mean("s3k", "median_mm"))),
      ("sig", derived(REAL_ONE_PASS, seeds_mean("baseline", "median_mm")))]),
    ("it is farther in every seed:\n  {} mm over three seeds, {} to {} ([held-out-end]",
     [("signed", at(REAL_END, "mean_paired_diff_mm")),
      ("signed", at(REAL_END, "mean_paired_diff_ci95_mm_over_seeds/0")),
      ("signed", at(REAL_END, "mean_paired_diff_ci95_mm_over_seeds/1"))]),
    ("on the recording's end neither ({} mm, [held-out-end]",
     [("signed", at(REAL_END_ADAPT, "over_seeds/test_block/adapted_minus_control/mean_mm"))]),
    ("score within a tenth of a millimetre of the hand-drawn ones (three seeds: {} against {} mm mean, one\n"
     "  seed {} mm worse,",
     [mm(AUTO_CROPS, f"over_seeds/{m}_mean_mm") for m in ("auto", "hand")]
     + [mm(AUTO_CROPS, "seeds/2/auto_minus_hand/mean_mm")]),
    # The label curve.
    ("to match S3K's median at 10 ({} mm; labels only at 20: {} mm) and does not reach S3K's RMS at 10"
     " ({} mm) even with 100 ({} mm: one seed in three keeps a tail, {}-{} mm). S3K at 20 labels: {} mm"
     " median ({}-{}).",
     [mm(CURVE, "curve/s3k/10/median_mm/mean"), mm(CURVE, "curve/labels_only/20/median_mm/mean"),
      mm(CURVE, "curve/s3k/10/rms_mm/mean"), mm(CURVE, "curve/labels_only/100/rms_mm/mean"),
      mm(CURVE, "curve/labels_only/100/rms_mm/min"), mm(CURVE, "curve/labels_only/100/rms_mm/max"),
      mm(CURVE, "curve/s3k/20/median_mm/mean"), mm(CURVE, "curve/s3k/20/median_mm/min"),
      mm(CURVE, "curve/s3k/20/median_mm/max")]),
    ("{}-{} CPU-minutes per S3K model, {}-{} per labels-only one",
     [("d1", derived(CURVE, _curve(m, "train_cpu_minutes", f)))
      for m in ("s3k", "labels_only") for f in (min, max)]),
    ("more labels buy little: S3K {} mm median at 10 labels and {} at 100, labels only {} and {}",
     [mm(PLUSH_CURVE, f"curve/{m}/{n}/median_mm/mean") for m in ("s3k", "labels_only") for n in (10, 100)]),
    ("its RMS stays {}-{} mm at every count, S3K's {}-{} mm",
     [("sig", derived(PLUSH_CURVE, _curve(m, "rms_mm", f)))
      for m in ("labels_only", "s3k") for f in (min, max)]),
    ("succeeds {}/180 with either detector ({}/180 with true keypoints;",
     [("d0", derived(ROBOT, lambda d, m=m: d["grasp_success"][m] * d["grasp_success"]["trials_in_all"]))
      for m in ("s3k", "ground_truth")]),
    ("ends at {}% insertions in each of 3 seeds, the beta-VAE agent on the same views at {}%",
     [pct(ROBOT, "rl_final_success/keypoints/min"), pct(ROBOT, "rl_final_success/beta_vae/mean")]),
    # Cameras outside the training rig.
    ("keep the in-range median ({}-{}x); cameras lower than any in training (10-20° elevation) do not"
     " ({}-{}x)",
     [("d2", _ratios("scene_rig", ("far", "wide"), f)) for f in (min, max)]
     + [("d2", _ratios("scene_rig", ("low",), f)) for f in (min, max)]),
    ("`s3k simulate --elevation 10,70`: {}-{}x, and on the usual cameras {} mm median against {};",
     [("d2", _ratios("wider_rig", ("low",), f)) for f in (min, max)]
     + [mm(WIDE, "models/s3k_wider_rig/median_mm/mean"), mm(WIDE, "models/s3k_scene_rig/median_mm/mean")]),
    ("nearly overhead (75-85°) give {}-{}x:",
     [("d2", _ratios("scene_rig", ("high",), f)) for f in (min, max)]),
    ("their 2D error is {}x the in-range one ({} px against {}), and at equal 2D error their narrow angles"
     " would give {}x the 3D error",
     [("d2", derived(DIAGNOSIS, lambda d: value_at(d, "rigs/high/diagnosis/fine_2d_median_px")
                     / value_at(d, "rigs/train/diagnosis/fine_2d_median_px"))),
      mm(DIAGNOSIS, "rigs/high/diagnosis/fine_2d_median_px"),
      mm(DIAGNOSIS, "rigs/train/diagnosis/fine_2d_median_px"),
      ("d2", at(DIAGNOSIS, "rigs/high/diagnosis/triangulation_floor_ratio"))]),
    # The Speed table.
    ("| {} CPU-min (coarse pass {}, crops {}, refining pass {}); labels only {}; `--preset box-fast` {} |",
     [("d1", at(SPEED, "s3k/train_cpu_minutes/mean"))]
     + [("d1", at(SPEED, f"stages/train_s3k/{s}/cpu_min")) for s in ("coarse", "crops", "fine")]
     + [("d1", at(SPEED, "labels_only/train_cpu_minutes/mean")),
        ("d1", at(FAST, "s3k/train_cpu_minutes/mean"))]),
    ("| {} frames/s (one thread {});",
     [("d0", at(QUIET, "inference_benchmark/threads_2/two_pass_frames_per_s_median")),
      ("d0", at(QUIET, "inference_benchmark/threads_1/two_pass_frames_per_s_median"))]),
    ("`+modified`), {} frames/s |", [("d0", at(QUIET, "trained_detector/threads_2/frames_per_s_median"))]),
    ("([inference-cpu-batch1.json](docs/results/benchmarks/inference-cpu-batch1.json)) | {} frames/s |",
     [("d0", at(ONE_PASS, "pipelines/one_pass/frames_per_s"))]),
]



def test_the_rounding_rule():
    assert [sig(v) for v in (37.2457, 34.0487, 0.2761, 118.3, 2.5698, 13.93, 4.69)] == \
        ["37.2", "34.0", "0.28", "118", "2.57", "13.9", "4.69"]


def test_every_readme_figure_equals_its_json():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert mismatches(text, loader(), FIGURES) == []


def test_every_cited_json_is_linked_from_the_readme():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    files = {BOX, FAST, FIVE, PLUSH, MUGS, INSERTION, DISTRACTORS, REAL, REAL_ONE_PASS, REAL_HELD_OUT,
             AUTO_CROPS, REAL_END, REAL_END_ADAPT, REAL_PRETRAINED, REAL_PRETRAINED_LABELS_ONLY,
             PLUSH_PRETRAINED, CURVE, PLUSH_CURVE, DIAGNOSIS, SPEED, QUIET, ONE_PASS, DEMO, ROBOT, WIDE}
    assert [f for f in sorted(files) if f"]({f})" not in text] == []


@pytest.mark.parametrize("old, new", [("37.2 mm (34.0, 35.5, 42.2)", "37.3 mm (34.1, 35.5, 42.2)"),
                                      ("| 11.4 CPU-min (coarse", "| 11.5 CPU-min (coarse")])
def test_an_edited_readme_figure_fails(old, new):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert text.count(old) == 1
    assert mismatches(text.replace(old, new), loader(), FIGURES) != []


def test_a_changed_json_value_fails():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    load = loader()
    load(MUGS)["labels_only"]["rms_mm"]["mean"] = 37.31
    bad = mismatches(text, load, FIGURES)
    assert len(bad) == 1 and "should read 37.3" in bad[0]
