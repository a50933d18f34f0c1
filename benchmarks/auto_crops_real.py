"""Automatic crop boxes against the hand boxes on the real recording: the same S3K training (the box's preset,
the held-out split, the same seed) on the import cropped with the hand boxes of ``scripts/real-recording.sh``
and on the import cropped with the boxes ``s3k crops`` found after a brief labels-only pass on whole
frames.

Both runs come from ``scripts/real-comparison.sh`` (``CROPS=hand`` and ``CROPS=auto``, ``MODELS=s3k``). Each
is scored on its own dataset's test frames against the proofread labels triangulated from every labelled view
(mm, as ``s3k evaluate``); the paired difference (auto minus hand, over the points both place) with its 95%
bootstrap interval over frames. The two imports recalibrate the defective camera each on their own, so
their references can differ slightly: the calibrations' largest difference is reported beside.

    python benchmarks/auto_crops_real.py --hand /tmp/real-held --auto /tmp/real-auto --seeds 0 \
        [--out docs/results/real/held-out/auto-crops.json]
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

from benchmarks.common import git_revision, machine_info, t_interval, write_and_emit  # noqa: E402
from benchmarks.real_comparison import distances  # noqa: E402
from s3k.base.label_reference import bootstrap_ci  # noqa: E402
from s3k.data import Dataset  # noqa: E402
from s3k.detector import Detector  # noqa: E402


def summary(d: np.ndarray) -> dict:
    v = d[np.isfinite(d)]
    return {
        "median_mm": float(np.median(v)),
        "mean_mm": float(v.mean()),
        "rms_mm": float(np.sqrt((v**2).mean())),
        "points": int(v.size),
    }


def calibration_difference(a: Path, b: Path) -> dict:
    """The largest difference between two anipose calibrations of the same cameras: camera centres (mm),
    focal lengths (relative)."""
    from s3k.data.formats.anipose import read_anipose_calibration

    ra, rb = read_anipose_calibration(a), read_anipose_calibration(b)
    ca, cb = ra.cameras.centres().numpy(), rb.cameras.centres().numpy()
    fa, fb = ra.cameras.K[:, 0, 0].numpy(), rb.cameras.K[:, 0, 0].numpy()
    return {"centre_mm": float(np.linalg.norm(ca - cb, axis=-1).max()),
            "focal_relative": float(np.abs(fa / fb - 1).max())}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hand", required=True, help="WORK of scripts/real-comparison.sh with the hand boxes")
    p.add_argument("--auto", required=True, help="WORK of scripts/real-comparison.sh with CROPS=auto")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)
    work = {"hand": Path(a.hand), "auto": Path(a.auto)}
    data = {k: Dataset.open(w / "crop", cache="none") for k, w in work.items()}
    test = np.asarray(data["hand"].frames("test"))
    if not np.array_equal(test, np.asarray(data["auto"].frames("test"))):
        raise SystemExit("the two imports hold out different test frames: import both with the same split")
    seeds = {}
    for seed in a.seeds:
        d = {
            k: distances(Detector.load(w / "runs" / f"s3k-seed{seed}", "cpu"), data[k], test)[1]
            for k, w in work.items()
        }
        both = np.isfinite(d["hand"]) & np.isfinite(d["auto"])
        diff = np.where(both, d["auto"] - d["hand"], np.nan)
        seeds[seed] = {
            "hand": summary(d["hand"]),
            "auto": summary(d["auto"]),
            "auto_minus_hand": {
                "mean_mm": float(np.nanmean(diff)),
                "ci95_mm": bootstrap_ci(diff),
                "points": int(both.sum()),
            },
        }
        s = seeds[seed]
        print(
            f"seed {seed}: hand boxes {s['hand']['median_mm']:.2f} mm median, "
            f"{s['hand']['mean_mm']:.2f} mean; "
            f"automatic {s['auto']['median_mm']:.2f} / {s['auto']['mean_mm']:.2f}; auto - hand "
            f"{s['auto_minus_hand']['mean_mm']:+.3f} mm (95% CI {s['auto_minus_hand']['ci95_mm']})",
            flush=True,
        )
    crops = json.loads((work["auto"] / "crops.json").read_text())
    gains = [s["auto_minus_hand"]["mean_mm"] for s in seeds.values()]
    result = {
        "command": shlex.join(
            ["python", "benchmarks/auto_crops_real.py", *(sys.argv[1:] if argv is None else argv)]
        ),
        "revision": git_revision(),
        "machine": machine_info(),
        "runs": f"WORK=W SEEDS={max(a.seeds) + 1} MODELS=s3k STEPS=2500 THREADS=1 SCALE=0.5 "
        "TEST_FRAMES=blocks "
        "TRAIN_OPTIONS='--preset box-headline --layout-tol 0' bash scripts/real-comparison.sh, with "
        "CROPS=auto for the automatic boxes",
        "boxes": {
            "hand": "scripts/real-recording.sh (512 x 512 px)",
            "auto": crops["crop"],
            "auto_notes": {
                c: {"labels_outside_detections": len(v["labels_outside"]), "box": v["box"]}
                for c, v in crops["cameras"].items()
            },
        },
        "image_size": {k: list(ds.image_size) for k, ds in data.items()},
        "test_frames": int(len(test)),
        "calibrations_differ": calibration_difference(work["hand"] / "calibration_fixed.toml",
                                                      work["auto"] / "calibration_fixed.toml"),
        "seeds": seeds,
        "over_seeds": {
            "auto_minus_hand_mean_mm": float(np.mean(gains)),
            "ci95_mm": t_interval(gains),
            **{f"{k}_{f}": float(np.mean([s[k][f] for s in seeds.values()]))
               for k in ("hand", "auto") for f in ("median_mm", "mean_mm")},
        },
    }
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
