"""A trained detector's 3D points on a dataset's frames, through two paths of ``s3k.Detector``: the fast CPU
path (the default) against the plain path (``fast=False``), or float32 against another ``--precision``.

Prints the distance between the two paths' points in millimetres (median, 95th percentile, largest, over
the points both find) and whether they find the same points; the last line is one JSON object with the
machine. The inference benchmark (``benchmarks/inference.py``) makes the same comparison on an untrained
network and noise; this one on what a user runs.

Example::

    python benchmarks/same_points.py --run runs/box --data data/box384 --frames 40
    python benchmarks/same_points.py --run runs/box --data data/box384 --precision bfloat16
    python benchmarks/same_points.py --run runs/box --data data/box384 --threads 2 --time 5  # and its speed
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision  # noqa: E402

MM = {"m": 1000.0, "cm": 10.0, "mm": 1.0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="a run folder of s3k train (one pass or --two-pass)")
    p.add_argument("--data", required=True, help="a dataset folder of frames at the run's frame size")
    p.add_argument("--split", default="test", help="frames of this split (default test)")
    p.add_argument("--frames", type=int, default=40, help="at most this many frames (default 40)")
    p.add_argument("--precision", default="float32", choices=("float32", "bfloat16", "float16"),
                   help="float32 (default): fast path against plain path; else this precision against "
                        "float32 on the fast path")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--time", type=int, default=0, metavar="ROUNDS",
                   help="then time the first path one frame at a time over the frames, ROUNDS rounds "
                        "(milliseconds per frame per round, and their median)")
    args = p.parse_args(argv)
    if args.time < 0:
        p.error(f"--time {args.time}: expected a number of rounds, 0 or more")

    from s3k.data import Dataset
    from s3k.detector import Detector

    torch.set_num_threads(args.threads)
    ds = Dataset.open(args.data)
    ids = ds.frames(args.split)[: args.frames]
    images, cams = ds.images(ids), ds.calibration(ids, np.float64)
    if args.precision == "float32":
        a, b = Detector.load(args.run, "cpu"), Detector.load(args.run, "cpu", fast=False)
        first, what = "fast path", "fast path against plain path, float32"
    else:
        a, b = Detector.load(args.run, "cpu", args.precision), Detector.load(args.run, "cpu")
        first, what = args.precision, f"{args.precision} against float32, fast path"
    frame_cams = [cams[i] if cams.shape[0] == len(ids) else cams for i in range(len(ids))]
    dist, same = [], True
    for i, c in enumerate(frame_cams):  # one frame at a time, as a stream runs
        x, y = a(images[i], c), b(images[i], c)
        same &= bool(torch.equal(x.valid, y.valid))
        ok = x.valid & y.valid
        dist.append((x.X[ok] - y.X[ok]).norm(dim=-1))
    d = torch.cat(dist).double() * MM.get(ds.units, 1.0)
    result = {"command": shlex.join(["python", "benchmarks/same_points.py",
                                     *(sys.argv[1:] if argv is None else argv)]),
              "git_revision": git_revision(), "benchmark": "same_points", "what": what,
              "frames": len(ids), "points": len(d), "same_validity": same, "units": ds.units,
              "median_mm": float(d.median()), "p95_mm": float(d.quantile(0.95)), "max_mm": float(d.max())}
    print(f"{what}: {len(d)} points of {len(ids)} frames, 3D distance median {result['median_mm']:.2e} mm, "
          f"95% {result['p95_mm']:.2e}, largest {result['max_mm']:.2e}; same points found: {same}")
    if args.time:  # the comparison above traced and warmed the first path on these frames
        rounds = []
        for _ in range(args.time):
            t0 = time.perf_counter()
            for i, c in enumerate(frame_cams):
                a(images[i], c)
            rounds.append((time.perf_counter() - t0) / len(ids) * 1e3)
        ms = statistics.median(rounds)
        result["timing"] = {"path": first, "threads": args.threads,
                            "ms_per_frame_rounds": rounds, "ms_per_frame_median": ms,
                            "frames_per_s": 1e3 / ms}
        print(f"{result['timing']['path']}, {args.threads} thread(s), one frame at a time: {ms:.2f} ms per "
              f"frame, {1e3 / ms:.1f} frames/s (median of {args.time} rounds: "
              + ", ".join(f"{r:.2f}" for r in rounds) + " ms)")
    emit(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
