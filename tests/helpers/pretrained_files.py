"""The committed JSON of the pretrained encoder (docs/results/accuracy/pretrained) and the scratch U-Net's
figures each is set against, for the tests that tie pages' figures to them."""

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
ENCODER_CURVES = {5: CURVE_5, 10: CURVE, 20: CURVE_20}  # the encoder's box point at each label count


def side_by_side_cpu_ratio(load, model: str) -> float:
    """The encoder's CPU-minutes over the scratch model's for ``model`` (``s3k``, ``labels_only``) at 5 and
    20 labels, both trained on one machine: the sum of the two counts' means over seeds, each side."""
    def cpu(file: str, n: int) -> float:
        return load(file)["curve"][model][str(n)]["train_cpu_minutes"]["mean"]
    return sum(cpu(ENCODER_CURVES[n], n) for n in (5, 20)) / sum(cpu(SCRATCH_HERE, n) for n in (5, 20))
