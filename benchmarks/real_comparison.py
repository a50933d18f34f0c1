"""S3K against labels only on the real recording, per seed, from the runs of scripts/real-comparison.sh.

Each finished pair (``runs/s3k-seedN``, ``runs/baseline-seedN``) is evaluated on the dataset's 40 held-out
frames as ``s3k evaluate`` does: the recording has no 3D truth, so the 3D figure is the distance between the
model's 3D points and the proofread labels triangulated from every labelled view (mm). Per seed: both models'
mean and median distance, the paired difference of the means (S3K - labels only, over the same keypoints)
with a 95% bootstrap interval over frames, rms_px, and how much the views of each model disagree on the
unlabelled frames (what the self-supervised term reduces), and a two-pass run's CPU minutes. Over seeds: the
mean paired difference with a 95% t-interval (needs >= 2 seeds).

    python benchmarks/real_comparison.py [--work /tmp/real-work] [--out FILE.json]

Runs laid out otherwise, e.g. one ``scripts/real-example.sh`` folder per seed: ``--runs
'OUT/seed{seed}/run-{model}' --data OUT/seed0/crop --about 'how they were trained'`` (``{model}`` is ``s3k``
or ``baseline``; the distances are in mm, so any import of the recording's test frames scores them alike).
Two other families of runs on the same split, e.g. S3K with the pretrained encoder against S3K from scratch:
``--models pretrained scratch --runs 'DIR/{model}/s3k-seed{seed}'``, each ``DIR/NAME`` a ``runs`` folder
(the difference is then pretrained - scratch).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, t_interval, write_and_emit  # noqa: E402
from s3k.base.label_reference import bootstrap_ci  # noqa: E402
from s3k.data import Dataset  # noqa: E402
from s3k.data.frames import FrameStore  # noqa: E402
from s3k.detector import Detector  # noqa: E402
from s3k.inference.evaluate import evaluate_store  # noqa: E402
from s3k.run_folder import RunFolder  # noqa: E402


def distances(detector: Detector, ds: Dataset, ids) -> tuple[dict, np.ndarray]:
    """The metrics and the (frames, keypoints) mm distances to the triangulated labels (NaN where none)."""
    metrics, arrays = evaluate_store(
        detector, FrameStore(ds, ids, preload_mb=0, labels=True), 16, ds.units, label_reference=True
    )
    ok = arrays["X_valid"] & arrays["lab_valid"]
    d = np.where(ok, np.linalg.norm(arrays["X"] - arrays["lab_X"], axis=-1), np.nan)
    return metrics, d


def view_consistency(detector: Detector, ds: Dataset) -> float:
    """Median pixel distance, over the unlabelled frames, between each view's detection and the reprojection
    of the confidence-weighted triangulated point: the disagreement between views that S3K's self-supervised
    term reduces on those frames (a model whose views already agree leaves it little to do)."""
    from s3k.inference.predict import detect_store

    store = FrameStore(ds, np.asarray(ds.frames("unlabelled")), preload_mb=0)
    d = [
        np.linalg.norm(p.uv.numpy() - p.reproj.numpy(), axis=-1)[
            p.valid.numpy()[:, None, :].repeat(p.uv.shape[1], 1)
        ]
        for _, p in detect_store(detector, store, 16)
    ]
    return float(np.median(np.concatenate(d)))


def _cpu_minutes(run: Path) -> dict:
    """A two-pass run's CPU minutes per stage and in all (its ``cpu.json``); nothing for a one-pass run."""
    path = RunFolder(run).cpu
    if not path.is_file():
        return {}
    stages = {k: round(v / 60, 2) for k, v in json.loads(path.read_text()).items()}
    return {"cpu_minutes": round(sum(stages.values()), 1), "cpu_minutes_per_stage": stages}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", default="/tmp/real-work", help="the folder of scripts/real-comparison.sh")
    p.add_argument("--data", default=None, help="the dataset to evaluate on (default WORK/crop)")
    p.add_argument("--runs", default="{work}/runs/{model}-seed{seed}",
                   help="where each run is, with {work}, {model} (one of --models) and {seed} filled in")
    p.add_argument("--models", nargs=2, default=["s3k", "baseline"], metavar=("FIRST", "SECOND"),
                   help="the two models compared, the paired difference being FIRST - SECOND (default: s3k "
                   "baseline, the runs of scripts/real-comparison.sh); e.g. pretrained scratch with --runs "
                   "'DIR/{model}/s3k-seed{seed}'")
    p.add_argument("--about", help="how the runs were trained, for the JSON",
                   default="bash scripts/real-comparison.sh (3000 steps, 128 px crops, 10 labelled, "
                   "70 unlabelled, 40 test frames)")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)
    work = Path(a.work)
    ds = Dataset.open(Path(a.data) if a.data else work / "crop", cache="none")
    ids = np.asarray(ds.frames("test"))
    first, second = a.models
    if first == second:
        p.error(f"--models {first} {second}: give two different models")
    seeds, diffs = {}, []
    for seed in range(100):
        runs = {m: Path(a.runs.format(work=work, model=m, seed=seed)) for m in a.models}
        if not all(RunFolder(r).is_complete() for r in runs.values()):
            first_run = RunFolder(runs[first])
            if not (first_run.is_one_pass_run() or first_run.is_two_pass_run()):
                break
            continue
        detectors = {m: Detector.load(r, "cpu") for m, r in runs.items()}  # each read once
        (ms, ds_), (mb, db) = (distances(detectors[m], ds, ids) for m in a.models)
        both = np.isfinite(ds_) & np.isfinite(db)
        paired = np.where(both, ds_ - db, np.nan)
        diff = float(np.nanmean(paired))
        diffs.append(diff)
        seeds[seed] = {
            **{
                m: {
                    "mean_mm": float(np.nanmean(d[both])),
                    "median_mm": float(np.nanmedian(d[both])),
                    "rms_mm": float(np.sqrt(np.nanmean(d[both] ** 2))),
                    "ci95_mean_mm": bootstrap_ci(np.where(both, d, np.nan)),
                    "rms_px": met["rms_px"],
                    "labels_leave_one_view_out_median_px": met["labels_3d"]["labels_leave_one_view_out_px"][
                        "median"
                    ],
                    "unlabelled_view_disagreement_median_px": view_consistency(detectors[m], ds),
                    **_cpu_minutes(runs[m]),
                }
                for m, d, met in ((first, ds_, ms), (second, db, mb))
            },
            "paired_diff_mean_mm": diff,
            "paired_diff_ci95_mm": bootstrap_ci(paired),
            "points": int(both.sum()),
            "frames": int(len(ids)),
        }
        print(
            f"seed {seed}: {first} {seeds[seed][first]['mean_mm']:.3f} mm, {second} "
            f"{seeds[seed][second]['mean_mm']:.3f} mm, {first} - {second} {diff:+.3f} mm "
            f"(95% CI {seeds[seed]['paired_diff_ci95_mm']})",
            flush=True,
        )
    result = {
        "command": shlex.join(["python", "benchmarks/real_comparison.py",
                               *(sys.argv[1:] if argv is None else argv)]),
        "revision": git_revision(),
        "runs": a.about,
        "reference": "proofread labels triangulated from every labelled view (>= 2), test frames",
        "seeds": seeds,
        "seeds_done": len(seeds),
        "mean_paired_diff_mm": float(np.mean(diffs)) if diffs else None,
        "mean_paired_diff_ci95_mm_over_seeds": t_interval(diffs),
    }
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
