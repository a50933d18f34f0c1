"""Clicks needed to label a frame in ``s3k label``, counted by driving the app's API with a simulated
labeller.

The labeller knows where each keypoint truly is (the dataset's ground truth: the projection of its 3D point,
visible where the scene says so) and clicks it with Gaussian noise (``--noise`` px per axis). A position
within ``--tol`` px of the truth is good enough. Three ways of working, each on a fresh copy of the labels:

- ``every_view``: click every keypoint in every view where it is visible (what a 2D labelling tool needs).
- ``reprojection``: for each keypoint, click the first two views where it is visible; the app triangulates
  and reprojects it into the others; where a reprojection misses the truth by more than ``--tol`` in a view
  where the keypoint is visible, drag it there (one click) and look again.
- ``suggestions`` (with ``--run``): for each keypoint whose suggestion lies within ``--tol`` of the truth in
  every view where it is visible, accept it (one click, the app's ``a``); label the others the
  ``reprojection`` way.

Each way is scored by the clicks per frame and by the 3D error of the triangulated labels (what the
supervised loss uses) against the ground truth.

    python benchmarks/label_clicks.py --data DATASET [--run RUN] [--frames 20] [--out clicks.json]

DATASET is a simulated dataset whose frames have labels (their visibility is the truth) and ``points3d``; its
labels are moved aside into a copy, so the dataset itself is not changed. The last line of output is one JSON
object (benchmarks/common.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import emit, git_revision, machine_info  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.experiments.label_clicks import ground_truth, run_way  # noqa: E402


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="simulated dataset with labels and points3d")
    p.add_argument("--run", help="trained run for the 'suggestions' way")
    p.add_argument("--frames", type=int, default=20, help="frames to label (the dataset's first N)")
    p.add_argument("--noise", type=float, default=0.5, help="click noise, px per axis (default 0.5)")
    p.add_argument("--tol", type=float, default=1.5, help="a position this close to the truth is kept (px)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="also write the result here (JSON)")
    args = p.parse_args(argv)
    started = time.perf_counter()
    data = Path(args.data)
    truth = ground_truth(data)
    frames = [int(f) for f in truth["frames"][: args.frames]]
    ways = ["every_view", "reprojection"] + (["suggestions"] if args.run else [])
    result: dict[str, Any] = {
        "benchmark": "label_clicks", "data": str(data), "run": args.run, "frames": len(frames),
        "cameras": len(truth["cameras"]), "keypoints": len(truth["keypoints"]), "image_size": truth["size"],
        "visible_views_per_frame": float(truth["visible"][: len(frames)].sum(axis=(1, 2)).mean()),
        "noise_px": args.noise, "tol_px": args.tol, "revision": git_revision(),
        "command": "python benchmarks/label_clicks.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    for way in ways:
        result[way] = run_way(way, data, truth, frames, Path(args.run) if args.run else None, args.noise,
                              args.tol, args.seed)
        print(f"{way}: {result[way]['clicks_per_frame']:.2f} clicks per frame "
              f"({result[way]['clicks_min']}-{result[way]['clicks_max']}), median 3D error "
              f"{result[way]['median_3d_error_mm']:.2f} mm", flush=True)
    result["seconds"] = time.perf_counter() - started
    result["machine"] = machine_info()
    if args.out:
        from s3k.base.fileio import atomic_write_json

        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(result, args.out)
    emit(result)
    return result


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        main()
