"""The committed JSON of the pretrained encoder (docs/results/accuracy/pretrained) and the scratch U-Net's
figures each is set against, for the tests that tie pages' figures to them, and the getters those tests
share."""

from helpers.figures import Getter, at, mm, value_at
from helpers.paths import REPO

PAGE = "docs/results/accuracy/pretrained/README.md"

HERE = "docs/results/accuracy/pretrained/"
STEP = HERE + "train-step.json"
CURVE = HERE + "label-curve-10.json"
CURVE_5 = HERE + "label-curve-5.json"
CURVE_5_CONTROL = HERE + "label-curve-5-scratch-seed0.json"
CURVE_5_POSES = HERE + "by-pose-5-seed0.json"
CURVE_20 = HERE + "label-curve-20.json"
CURVE_20_CONTROL = HERE + "label-curve-20-scratch-seed0.json"
CURVE_20_POSES = HERE + "by-pose-20-seed0.json"
CURVE_5_POSES_12 = HERE + "by-pose-5-seeds-1-2.json"
CURVE_20_POSES_12 = HERE + "by-pose-20-seeds-1-2.json"
SCRATCH_HERE = HERE + "scratch-curve/summary.json"
SCRATCH_CURVE = "docs/results/accuracy/label-curve/summary.json"
REAL = HERE + "real-held-out.json"
REAL_LABELS_ONLY = HERE + "real-held-out-labels-only.json"
REAL_SCRATCH = "docs/results/real/held-out/comparison.json"
MUGS = HERE + "mugs.json"
SCRATCH_MUGS = "docs/results/accuracy/headline-preset/category/summary.json"
MUGS_HERE = HERE + "mugs-scratch.json"
PLUSH = HERE + "plush.json"
SCRATCH_PLUSH = "docs/results/accuracy/headline-preset/plush/summary.json"
PLUSH_CONTROL = HERE + "plush-scratch-seed0.json"
PLUSH_HERE = HERE + "plush-scratch.json"
PLUSH_CONTROL_AGAIN = HERE + "plush-scratch-seed0-again.json"
OUTSIDE_20 = HERE + "outside-rig-20.json"
OUTSIDE_20_LABELS_ONLY = HERE + "outside-rig-20-labels-only.json"
INSERTION = HERE + "insertion.json"
SCRATCH_INSERTION = "docs/results/accuracy/headline-preset/insertion/summary.json"
INSERTION_CONTROL = HERE + "insertion-scratch-seed0.json"
INSERTION_HERE = HERE + "insertion-scratch.json"
INSERTION_POSES = HERE + "insertion-by-pose-s3k.json"
INSERTION_SEED0_POSES = HERE + "insertion-by-pose-seed0.json"
MUGS_POSES = HERE + "mugs-by-pose.json"  # its first run: the scratch seed-0 control
OUTSIDE_SEED0 = HERE + "outside-rig-s3k-seed0.json"
OUTSIDE_SCRATCH_SEED0 = "docs/results/accuracy/outside-rig/s3k-seed0-diagnosis.json"
ENCODER_CURVES = {5: CURVE_5, 10: CURVE, 20: CURVE_20}  # the encoder's box point at each label count


def side_by_side_cpu_ratio(load, model: str) -> float:
    """The encoder's CPU-minutes over the scratch model's for ``model`` (``s3k``, ``labels_only``) at 5 and
    20 labels, both trained on one machine: the sum of the two counts' means over seeds, each side."""
    def cpu(file: str, n: int) -> float:
        return load(file)["curve"][model][str(n)]["train_cpu_minutes"]["mean"]
    return sum(cpu(ENCODER_CURVES[n], n) for n in (5, 20)) / sum(cpu(SCRATCH_HERE, n) for n in (5, 20))


def page_words() -> str:
    """The pretrained page's text with every run of whitespace one space, for the tests of its sentences."""
    return " ".join((REPO / PAGE).read_text(encoding="utf-8").split())


def seed_gaps(encoder: str, scratch: str, path: str) -> Getter:
    """Per seed 0-2, the encoder's value at ``path`` (e.g. ``s3k/median_mm``) less the scratch model's."""
    return lambda load: [value_at(load(encoder), f"{path}/per_seed/{i}")
                         - value_at(load(scratch), f"{path}/per_seed/{i}") for i in range(3)]


def cpu_ratio(encoder: str, scratch: str, model: str) -> Getter:
    """The encoder's mean CPU-minutes per model over the scratch model's, for ``model`` of two scene
    summaries."""
    return lambda load: (load(encoder)[model]["train_cpu_minutes"]["mean"]
                         / load(scratch)[model]["train_cpu_minutes"]["mean"])


def real_row(file: str, seed: int) -> list[tuple[str, Getter]]:
    """A seed's row of a real-recording comparison of the encoder against scratch (``real_comparison.py
    --models pretrained scratch``): each model's mean and median distance, the paired difference with its
    interval over frames, each model's CPU-minutes."""
    s = f"seeds/{seed}"
    out = [mm(file, f"{s}/{m}/{k}") for m in ("pretrained", "scratch") for k in ("mean_mm", "median_mm")]
    out += [("d3", at(file, f"{s}/paired_diff_mean_mm"))]
    out += [("d3", at(file, f"{s}/paired_diff_ci95_mm/{i}")) for i in range(2)]
    return out + [("d1", at(file, f"{s}/{m}/cpu_minutes")) for m in ("pretrained", "scratch")]
