"""Adapting a trained S3K detector to a stretch of recording it never saw, from that stretch's frames alone.

The paper's domain-shift question on the real recording: runs of ``scripts/real-comparison.sh`` with
``TEST_FRAMES=blocks`` were trained with their 40 test frames held out in one contiguous block (no labelled
frame within 10 frames of it). Each S3K run is fine-tuned twice from its final state with the run's own
configuration and final learning rates (``s3k train --init-from RUN --steps N``), as many steps each:

- **adapted**: on a copy of the dataset whose test frames are unlabelled frames (their labels unused), so the
  self-supervised term sees the held-out stretch;
- **control**: on the dataset itself, so that what training longer alone does is measured beside it.

All three (the run, adapted, control) are scored on the test block against the proofread labels triangulated
from every labelled view (mm; the recording has no 3D truth) and on the labelled frames (the run's own labels:
adaptation must not make it worse there). Paired differences with 95% bootstrap intervals over frames per
seed, and t-intervals over seeds.

    python benchmarks/adapt_real.py --work /tmp/real-held --steps 500 [--seeds 0 1 2] [--out FILE.json]

Resumable: a finished fine-tune is kept (``s3k train --resume`` leaves a finished run as it is).
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import (  # noqa: E402
    fine_tune_argv,
    git_revision,
    machine_info,
    paired,
    t_interval,
    write_and_emit,
)
from benchmarks.real_comparison import distances  # noqa: E402
from s3k.data import Dataset  # noqa: E402
from s3k.detector import Detector  # noqa: E402
from s3k.experiments.adapt import held_out_as_unlabelled  # noqa: E402
from s3k.run_folder import RunFolder  # noqa: E402


def fine_tune(data: Path, run: Path, out: Path, steps: int, threads: int) -> None:
    """``s3k train DATA --init-from RUN --steps STEPS`` into ``out`` (resumed when begun, kept when done)."""
    cmd = fine_tune_argv(data, run, out, steps, threads)
    print("$", shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def scores(detector: Detector, ds: Dataset, ids: np.ndarray) -> np.ndarray:
    """(frames, keypoints) mm distances of ``detector``'s 3D points to the triangulated labels (NaN where
    none)."""
    return distances(detector, ds, ids)[1]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", default="/tmp/real-held", help="the folder of scripts/real-comparison.sh")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=500, help="fine-tuning steps (each pass of a two-pass run)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="JSON file for the figures")
    p.add_argument("--about", default="WORK=... SEEDS=3 STEPS=2500 THREADS=1 SCALE=0.5 TEST_FRAMES=blocks "
                   "TRAIN_OPTIONS='--preset box-headline --layout-tol 0' bash scripts/real-comparison.sh",
                   help="how the runs were trained, for the JSON (default: the held-out block's command)")
    a = p.parse_args(argv)
    work = Path(a.work)
    data = work / "crop"
    adapt_data = held_out_as_unlabelled(data, work / "crop-test-unlabelled")
    ds = Dataset.open(data, cache="none")
    test, labelled = np.asarray(ds.frames("test")), np.asarray(ds.frames("labelled"))
    seeds: dict[int, dict] = {}
    for seed in a.seeds:
        base = work / "runs" / f"s3k-seed{seed}"
        if not RunFolder(base).is_complete():
            print(f"seed {seed}: {base} is not finished; skipped", flush=True)
            continue
        runs = {"run": base, "adapted": work / "runs" / f"s3k-seed{seed}-adapted{a.steps}",
                "control": work / "runs" / f"s3k-seed{seed}-control{a.steps}"}
        fine_tune(adapt_data, base, runs["adapted"], a.steps, a.threads)
        fine_tune(data, base, runs["control"], a.steps, a.threads)
        detectors = {k: Detector.load(r, "cpu") for k, r in runs.items()}  # each run read once
        on_test = {k: scores(d, ds, test) for k, d in detectors.items()}
        on_lab = {k: scores(d, ds, labelled) for k, d in detectors.items()}
        seeds[seed] = {
            "test_block": {"adapted_minus_run": paired(on_test["adapted"], on_test["run"]),
                           "adapted_minus_control": paired(on_test["adapted"], on_test["control"]),
                           "control_minus_run": paired(on_test["control"], on_test["run"])},
            "labelled_frames": {"adapted_minus_run": paired(on_lab["adapted"], on_lab["run"]),
                                "adapted_minus_control": paired(on_lab["adapted"], on_lab["control"])},
        }
        t = seeds[seed]["test_block"]
        print(f"seed {seed}: test block, adapted - run {t['adapted_minus_run']['mean_diff_mm']:+.3f} mm "
              f"(95% CI {t['adapted_minus_run']['ci95_mm']}), adapted - control "
              f"{t['adapted_minus_control']['mean_diff_mm']:+.3f} mm; labelled frames, adapted - run "
              f"{seeds[seed]['labelled_frames']['adapted_minus_run']['mean_diff_mm']:+.3f} mm", flush=True)

    def over_seeds(where: str, what: str) -> dict:
        x = [s[where][what]["mean_diff_mm"] for s in seeds.values()]
        return {"mean_mm": float(np.mean(x)) if x else None, "ci95_mm": t_interval(x)}

    result = {
        "command": shlex.join(["python", "benchmarks/adapt_real.py",
                               *(sys.argv[1:] if argv is None else argv)]),
        "revision": git_revision(),
        "machine": machine_info(),
        "runs": a.about,
        "reference": "proofread labels triangulated from every labelled view (>= 2)",
        "test_frames": [int(test.min()), int(test.max())] if len(test) else None,
        "labelled_frames": labelled.tolist(),
        "steps": a.steps,
        "seeds": seeds,
        "over_seeds": {w: {k: over_seeds(w, k) for k in seeds[next(iter(seeds))][w]} for w in
                       ("test_block", "labelled_frames")} if seeds else {},
    }
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
