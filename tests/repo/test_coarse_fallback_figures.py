"""The coarse fallback's figures where the pages quote them (docs/accuracy.md, the README, the accuracy log,
the results index) read as docs/results/accuracy/coarse-fallback/summary.json, and the 10% margin's by-pose
reading as crops-256-margin-0.1/by-pose-s3k.json, to the digits shown (the rules of ``helpers.figures``)."""

from __future__ import annotations

from helpers.figures import Figures, Getter, loader, page_mismatches

SUMMARY = "docs/results/accuracy/coarse-fallback/summary.json"
BY_POSE = "docs/results/accuracy/crops-256-margin-0.1/by-pose-s3k.json"
OLD_BY_POSE = "docs/results/accuracy/crops-256/by-pose-s3k.json"
HEADLINE, LABELS_ONLY = "/tmp/lc5/work-scratch/L10/s3k", "/tmp/lc5/work-scratch/L10/labels_only"
FIVE, COMBO, MARGIN = "/tmp/lc5/work-scratch/L5/s3k", "/tmp/c2m/work/L10/s3k", "/tmp/m01/work/L10/s3k"
WITH, WITHOUT = "fallback", "refining only"
LID_UP, LID_ON_TABLE, SIDE = "normal down", "normal up", "on a side"  # as error_by_pose.py names the poses


def fig(config: str, way: str, key: str, seed: int | None = None, scale: float = 1.0) -> Getter:
    def get(load) -> float:
        entry = load(SUMMARY)["configurations"][config][way][key]
        return scale * (entry["mean"] if seed is None else entry["per_seed"][seed])
    return get


def rms(config: str, way: str, seed: int | None = None) -> tuple[str, Getter]:
    return "sig", fig(config, way, "rms_mm", seed)


def median(config: str, way: str) -> tuple[str, Getter]:
    return "sig", fig(config, way, "median_mm")


def runs(load) -> list[dict]:
    return list(load(SUMMARY)["runs"].values())


def rms_changes(load) -> list[float]:
    return [r[WITH]["rms_mm"] - r[WITHOUT]["rms_mm"] for r in runs(load)]


def count(test) -> tuple[str, Getter]:
    return "d0", lambda load: sum(test(d) for d in rms_changes(load))


STOOD_IN = ("d0", lambda load: sum(r["fallback_frames"] for r in runs(load)))
FRAMES = ("d0", lambda load: sum(r["frames"] for r in runs(load)))
MODELS = ("d0", lambda load: len(runs(load)))
LOWER, HIGHER, SAME = count(lambda d: d < -1e-9), count(lambda d: d > 1e-9), count(lambda d: abs(d) <= 1e-9)
MOST = ("d2", lambda load: max(rms_changes(load)))


def frames(config: str) -> list[tuple[str, Getter]]:
    return [("d0", lambda load, s=s: load(SUMMARY)["configurations"][config]["fallback_frames"][s])
            for s in range(3)]


def table_row(config: str) -> list[tuple[str, Getter]]:
    return [*frames(config), rms(config, WITHOUT), *[rms(config, WITHOUT, s) for s in range(3)],
            rms(config, WITH), *[rms(config, WITH, s) for s in range(3)], median(config, WITHOUT),
            median(config, WITH)]


def pose_range(file: str, pose: str, what: str, end: str, seeds: tuple[int, ...] = (0, 1, 2),
               first: int = 0) -> Getter:
    """The least or greatest (``end``) over the runs ``first + seeds`` of a pose's median (``median``) or
    lean into the box (``lean``: minus the mean offset along the lid's normal, per keypoint)."""
    def get(load) -> float:
        values: list[float] = []
        all_runs = list(load(file)["runs"].values())
        for seed in seeds:
            row = all_runs[first + seed]["by_pose"][pose]
            values += [-b[2] for b in row["bias_mm"]] if what == "lean" else [row["median_mm"]]
        return min(values) if end == "low" else max(values)
    return get


def span(file: str, pose: str, what: str, seeds: tuple[int, ...] = (0, 1, 2)) -> list[tuple[str, Getter]]:
    return [("d2", pose_range(file, pose, what, end, seeds)) for end in ("low", "high")]


def labelled_on_table(load, seed: int) -> int:
    return list(load(BY_POSE)["runs"].values())[seed]["labelled_poses"][LID_ON_TABLE]


def seed_median(pose: str, seed: int) -> tuple[str, Getter]:
    return "d2", lambda load: list(load(BY_POSE)["runs"].values())[seed]["by_pose"][pose]["median_mm"]


ACCURACY: Figures = [
    ("nothing trained\n([coarse-fallback/summary.json](results/accuracy/coarse-fallback/summary.json)):"
     " {} of {} test frames over\n{} models stood in", [STOOD_IN, FRAMES, MODELS]),
    ("The headline preset's S3K RMS at ten labels falls from {} to {} mm ({} to {} in seed 0, {} to {} in"
     " seed 1) and its median stays at {}; 256 px crops with a 10% margin fall from {} to {} mm RMS (seed 0:"
     " {} to {}, one frame); labels only at ten labels from {} to {} mm, lower in every seed. The RMS is"
     " lower in {} models, higher in {} (by at most {} mm) and the same in {}.",
     [rms(HEADLINE, WITHOUT), rms(HEADLINE, WITH), rms(HEADLINE, WITHOUT, 0), rms(HEADLINE, WITH, 0),
      rms(HEADLINE, WITHOUT, 1), rms(HEADLINE, WITH, 1), median(HEADLINE, WITH), rms(COMBO, WITHOUT),
      rms(COMBO, WITH), rms(COMBO, WITHOUT, 0), rms(COMBO, WITH, 0), rms(LABELS_ONLY, WITHOUT),
      rms(LABELS_ONLY, WITH), LOWER, HIGHER, MOST, SAME]),
]

RESULTS: Figures = [
    ("| headline preset's S3K RMS {} -> {} mm, median {} -> {}; 256 px crops with a 10% margin {} -> {} mm"
     " RMS |",
     [rms(HEADLINE, WITHOUT), rms(HEADLINE, WITH), median(HEADLINE, WITHOUT), median(HEADLINE, WITH),
      rms(COMBO, WITHOUT), rms(COMBO, WITH)]),
]

LOG: Figures = [
    ("| S3K, `box-headline`, 10 labels | {}, {}, {} | {} ({}, {}, {}) | {} ({}, {}, {}) | {} / {} |",
     table_row(HEADLINE)),
    ("| labels only, `box-headline`, 10 labels | {}, {}, {} | {} ({}, {}, {}) | {} ({}, {}, {}) | {} / {} |",
     table_row(LABELS_ONLY)),
    ("| S3K, `box-headline`, 5 labels | {}, {}, {} | {} ({}, {}, {}) | {} ({}, {}, {}) | {} / {} |",
     table_row(FIVE)),
    ("| S3K, 256 px crops, 10% margin | {}, {}, {} | {} ({}, {}, {}) | {} ({}, {}, {}) | {} / {} |",
     table_row(COMBO)),
    ("| S3K, 192 px crops, 10% margin | {}, {}, {} | {} | {} | {} / {} |",
     [*frames(MARGIN), rms(MARGIN, WITHOUT), rms(MARGIN, WITH), median(MARGIN, WITHOUT),
      median(MARGIN, WITH)]),
    ("the 5-label seed 0's RMS rises by {} mm, its seed 1's share within 10 mm falls from\n{}% to {}%",
     [("d2", lambda load: fig(FIVE, WITH, "rms_mm", 0)(load) - fig(FIVE, WITHOUT, "rms_mm", 0)(load)),
      ("sig", fig(FIVE, WITHOUT, "pck_10mm", 1, 100.0)), ("sig", fig(FIVE, WITH, "pck_10mm", 1, 100.0))]),
    ("with the lid up the\ncorners are at {}-{} mm median (against {}-{}), on a side {}-{} (against {}-{})."
     " With the lid\non the table the lean ranges over {}-{} mm (against {}-{}) and that pose's median over"
     " {}-{} mm\n(against {}-{}).",
     [*span(BY_POSE, LID_UP, "median"), *span(OLD_BY_POSE, LID_UP, "median"), *span(BY_POSE, SIDE, "median"),
      *span(OLD_BY_POSE, SIDE, "median"), *span(BY_POSE, LID_ON_TABLE, "lean"),
      *span(OLD_BY_POSE, LID_ON_TABLE, "lean"), *span(BY_POSE, LID_ON_TABLE, "median"),
      *span(OLD_BY_POSE, LID_ON_TABLE, "median")]),
    ("lean {}-{} mm into the box with the lid on the table (the others {}-{}) and whose median there is"
     "\n{} mm (the others {} and {})",
     [*span(BY_POSE, LID_ON_TABLE, "lean", (2,)), *span(BY_POSE, LID_ON_TABLE, "lean", (0, 1)),
      seed_median(LID_ON_TABLE, 2), seed_median(LID_ON_TABLE, 0), seed_median(LID_ON_TABLE, 1)]),
    ("its ten labelled frames show the lid on the table {} times, the other\nseeds' {} times",
     [("d0", lambda load: labelled_on_table(load, 2)), ("d0", lambda load: labelled_on_table(load, 0))]),
]

README: Figures = [
    ("read again on the same preset's 10-label models trained on one machine,\n  S3K's RMS falls from {}"
     " to {} mm, its median unchanged", [rms(HEADLINE, WITHOUT), rms(HEADLINE, WITH)]),
]

PAGES = {"docs/accuracy.md": ACCURACY, "README.md": README, "docs/results/accuracy/README.md": RESULTS,
         "docs/accuracy-log.md": LOG}


def test_every_coarse_fallback_figure_equals_its_json():
    assert page_mismatches(PAGES, loader()) == {page: [] for page in PAGES}


def test_the_claims_in_words_hold():
    """"labels only ... lower in every seed", "none of box-precise's or of the 20-label models'", and the
    by-pose file reads the summary's 10%-margin models (their medians over all poses)."""
    load = loader()
    configs = load(SUMMARY)["configurations"]
    assert all(w < wo for w, wo in zip(configs[LABELS_ONLY][WITH]["rms_mm"]["per_seed"],
                                       configs[LABELS_ONLY][WITHOUT]["rms_mm"]["per_seed"]))
    assert configs["/tmp/c256/work/L10/s3k"]["fallback_frames"] == [0, 0, 0]
    assert configs["/tmp/lc5/work-scratch/L20/s3k"]["fallback_frames"] == [0, 0, 0]
    assert labelled_on_table(load, 1) == labelled_on_table(load, 0)  # "the other seeds'": both
    for seed, run in enumerate(load(BY_POSE)["runs"].values()):
        assert abs(run["all"]["median_mm"] - configs[COMBO][WITH]["median_mm"]["per_seed"][seed]) < 1e-4
