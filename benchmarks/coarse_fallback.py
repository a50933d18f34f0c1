"""The coarse pass standing in for a refining pass that breaks a rigid layout, read on trained detectors.

A rigid two-pass detector (``--layout-tol`` above 0) fits the labelled layout onto each frame's refining
points. Where the rigid read-out finds no set of keypoints that holds the layout, the refining points are
left as they are: part of the object was read elsewhere, sometimes tens of millimetres off. Since the
fallback (:func:`s3k.readout.coarse_stands_in`), such a frame takes the coarse read-out when the coarse
points hold the layout. Each RUN is read on DATA's ``--split`` with the fallback on (s3k's default) and off
(``TwoPassDetector(coarse_fallback=False)``, as before it); nothing is trained.

Printed and written per run: median and RMS 3D error, the share within 10 mm (``s3k evaluate``'s metrics)
both ways, and the frames the coarse pass stood in for; per configuration (the run's path less its
``-seedN``), the mean of each figure over its seeds.

    python benchmarks/coarse_fallback.py RUN DATA [RUN DATA ...] [--workers 2] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import add_run_data_arguments, run_data_pairs, split_store, write_runs  # noqa: E402

FIGURES = ("median_mm", "rms_mm", "pck_10mm")


def read(run: str, data: str, split: str) -> dict:
    """``run`` read on ``data``'s ``split`` with the coarse fallback on and off."""
    import torch

    from s3k.detector import Detector, TwoPassDetector
    from s3k.inference.evaluate import evaluate_store

    torch.set_num_threads(1)
    ds, store = split_store(data, split)
    detector = Detector.load(run, "cpu")
    if not isinstance(detector, TwoPassDetector):
        raise SystemExit(f"{run}: not a two-pass run; the fallback is a two-pass detector's")
    out: dict = {"data": data}
    for name, on in (("fallback", True), ("refining only", False)):
        detector.coarse_fallback = on
        metrics, _ = evaluate_store(detector, store, units=ds.units)
        out[name] = {k: metrics[k] for k in FIGURES}
        if on:
            out["fallback_frames"] = metrics["two_pass"]["coarse_fallback_frames"]
            out["frames"] = metrics["n_frames"]
        print(f"{run} {name}: median {metrics['median_mm']:.3f} mm, RMS {metrics['rms_mm']:.3f} mm, "
              f"within 10 mm {100 * metrics['pck_10mm']:.1f}%", flush=True)
    return out


def configurations(runs: dict[str, dict]) -> dict[str, dict]:
    """Per configuration (the run's path less ``-seedN``): each way's figures, per seed and their mean, and
    the frames stood in for, per seed."""
    groups: dict[str, list[dict]] = {}
    for run, result in runs.items():
        groups.setdefault(re.sub(r"-seed\d+$", "", run.rstrip("/")), []).append(result)
    out = {}
    for name, results in groups.items():
        entry: dict = {"seeds": len(results), "fallback_frames": [r["fallback_frames"] for r in results]}
        for way in ("fallback", "refining only"):
            entry[way] = {k: {"mean": float(np.mean([r[way][k] for r in results])),
                              "per_seed": [r[way][k] for r in results]} for k in FIGURES}
        out[name] = entry
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_data_arguments(p)
    p.add_argument("--workers", type=int, default=1, help="runs read side by side, one thread each")
    a = p.parse_args(argv)
    if a.workers < 1:
        p.error(f"--workers {a.workers}: at least 1")
    pairs = run_data_pairs(p, a)
    for run, _ in pairs:
        if not Path(run).is_dir():
            p.error(f"{run}: no such run folder")
    with ProcessPoolExecutor(a.workers) as pool:
        results = list(pool.map(read, *zip(*pairs), [a.split] * len(pairs)))
    runs = {run: r for (run, _), r in zip(pairs, results)}
    write_runs("benchmarks/coarse_fallback.py", argv, a, runs, {"configurations": configurations(runs)})


if __name__ == "__main__":
    main()
