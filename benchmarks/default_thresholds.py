"""Do the documented thresholds work on a short run and on the full preset? ``s3k track --min-weight 0.5``
(docs/tracks.md) and the labelling app's accept (a suggested view is accepted where its calibrated confidence
is at least 0.5) compare each view's calibrated confidence, not the raw weight that a short run keeps small.

For each run, on every frame of the dataset that is not labelled (its unlabelled and test frames): the median
raw weight and calibrated confidence of the views, the share of points that ``--min-weight 0.5`` keeps
triangulated, the share of views the app's accept takes, and on the test frames the share of accepted views
within two target widths of the proofread 2D label (what a confidence of 0.5 promises: about half, or more).

    python benchmarks/default_thresholds.py --data /tmp/real-held/crop \
        --run short=/tmp/real-held/runs/s3k-seed0-short200 --run full=/tmp/real-held/runs/s3k-seed0 \
        [--out docs/results/real/default-thresholds.json]
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402
from s3k.data import Dataset  # noqa: E402
from s3k.detector import Detector  # noqa: E402

THRESHOLD = 0.5  # the documented --min-weight and the app's accept


def shares(detector: Detector, ds: Dataset, batch: int = 8) -> dict:
    """The figures of one run on ``ds``'s frames that are not labelled (module docstring)."""
    test = set(int(f) for f in ds.frames("test"))
    ids = np.asarray(ds.frames(["unlabelled", "test"]))
    weights, confidence, valid, hits = [], [], [], []
    for i in range(0, len(ids), batch):
        chunk = ids[i:i + batch]
        with torch.no_grad():
            out = detector(ds.images(chunk), ds.calibration(chunk), min_weight=THRESHOLD)
        weights.append(out.weights.numpy().ravel())
        conf = out.confidence.numpy()
        confidence.append(conf.ravel())
        valid.append(out.valid.numpy().ravel())
        on_test = np.array([int(f) in test for f in chunk])
        if on_test.any():
            uv, mask = ds.labels(chunk[on_test])
            err = np.linalg.norm(out.uv.numpy()[on_test] - uv, axis=-1)
            assert out.pixel_maps is not None  # network pixels -> image pixels, per view (as the app does)
            scale = out.pixel_maps[..., :2, :2].det().abs().sqrt().numpy()[on_test]  # (B, C)
            width = 2 * float(detector.meta.sigma) / scale[..., None]  # two target widths, image pixels
            accepted = (conf[on_test] >= THRESHOLD) & mask
            hits.append((err <= width)[accepted].astype(float))
    w, c, v = np.concatenate(weights), np.concatenate(confidence), np.concatenate(valid)
    h = np.concatenate(hits) if hits else np.zeros(0)
    return {"frames": int(len(ids)), "median_raw_weight": float(np.median(w)),
            "median_confidence": float(np.nanmedian(c)),
            "track_min_weight_valid_share": float(v.mean()),
            "app_accept_share_of_views": float(np.mean(c >= THRESHOLD)),
            "raw_weight_above_threshold_share": float(np.mean(w >= THRESHOLD)),
            "accepted_test_views": int(h.size),
            "accepted_within_two_widths_share": float(h.mean()) if h.size else None,
            "calibrated": detector.meta.calibration is not None}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="the dataset the runs were trained on")
    p.add_argument("--run", action="append", required=True, metavar="NAME=RUN", help="a run folder, named")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    ds = Dataset.open(a.data, cache="none")
    runs = {}
    for item in a.run:
        name, _, path = item.partition("=")
        runs[name] = {"run": path, **shares(Detector.load(path, "cpu"), ds)}
        r = runs[name]
        print(f"{name}: raw weight median {r['median_raw_weight']:.3f}, "
              f"calibrated {r['median_confidence']:.3f}; "
              f"--min-weight 0.5 keeps {100 * r['track_min_weight_valid_share']:.1f}% of points, the app "
              f"accepts {100 * r['app_accept_share_of_views']:.1f}% of views (raw weight >= 0.5: "
              f"{100 * r['raw_weight_above_threshold_share']:.1f}%); accepted test views within two widths: "
              f"{r['accepted_within_two_widths_share']}", flush=True)
    result = {"command": shlex.join(["python", "benchmarks/default_thresholds.py",
                                     *(sys.argv[1:] if argv is None else argv)]),
              "revision": git_revision(), "machine": machine_info(), "threshold": THRESHOLD, "runs": runs}
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
