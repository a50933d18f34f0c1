"""Batched weighted triangulation throughput (s3k.geometry.triangulate_rays) against a per-point OpenCV loop.

A rig of V cameras about 1 m from the workspace looks at N random points; the noise-free rays through each
point's projections, with random confidence-like weights, are solved in one batched call (float32, all torch
threads, best of several repeats). The same weighted least-squares problem is then solved point by point with
OpenCV (``cv2.solve`` on the stacked 3V x 3 system) on a subset, and its rate is extrapolated to a second.

    python benchmarks/triangulation.py                 # 1M points x 4 views
    python benchmarks/triangulation.py --points 200000 --repeats 3

The last line of output is one JSON object (see benchmarks/common.py) with ``solves_per_s``,
``opencv_loop_solves_per_s``, the errors of both against the true points, and the machine. Both library paths
are timed: the default eager solve and ``fused=True`` (one torch.compile'd loop; its first call compiles);
``solves_per_s`` is the faster, named in ``best_path``, and each has its own field.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import cv2
import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, machine_info, matmul_flops  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.geometry import triangulate_rays  # noqa: E402

TARGET = 10e6  # solves per second (docs/method.md#performance-targets)


def make_rays(n: int, views: int, seed: int, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """Rays from V camera centres on a ~1 m sphere through N points of a 30 cm workspace.

    Returns:
        origins (N, V, 3), directions (N, V, 3) unit, weights (N, V) in [0.05, 1] (all ``dtype``) and the
        true points (N, 3) in float64.
    """
    gen = torch.Generator().manual_seed(seed)
    centres = torch.nn.functional.normalize(torch.randn(views, 3, generator=gen, dtype=torch.float64), dim=-1)
    X = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.3
    d = torch.nn.functional.normalize(X[:, None, :] - centres, dim=-1)
    w = 0.05 + 0.95 * torch.rand(n, views, generator=gen, dtype=torch.float64)
    o = centres.expand(n, views, 3)
    return o.to(dtype).contiguous(), d.to(dtype).contiguous(), w.to(dtype), X


def opencv_loop(o: np.ndarray, d: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Per point: the weighted system sqrt(w) (I - d d^T) x = sqrt(w) (I - d d^T) a, least squares by cv2."""
    n, v, _ = o.shape
    out = np.empty((n, 3))
    eye = np.eye(3)
    start = time.perf_counter()
    for i in range(n):
        P = eye - d[i, :, :, None] * d[i, :, None, :]  # (V, 3, 3)
        s = np.sqrt(w[i])[:, None, None]
        A = (s * P).reshape(3 * v, 3)
        b = (s * (P @ o[i, :, :, None])).reshape(3 * v, 1)
        _, x = cv2.solve(A, b, flags=cv2.DECOMP_SVD)
        out[i] = x[:, 0]
    return out, time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=1_000_000, help="points solved per batched call")
    parser.add_argument("--views", type=int, default=4, help="views (rays) per point")
    parser.add_argument("--repeats", type=int, default=7, help="timed batched calls; the best one counts")
    parser.add_argument("--cv-points", type=int, default=5000, help="points solved by the per-point loop")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--matmul-seconds", type=float, default=2.0, help="time measuring matmul FLOP/s")
    parser.add_argument("--no-fused", action="store_true", help="skip the torch.compile'd path")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)

    o, d, w, X = make_rays(args.points, args.views, args.seed, dtype)
    paths = {"eager": False} if args.no_fused else {"eager": False, "fused": True}
    times: dict[str, list[float]] = {}
    errors: dict[str, float] = {}
    compile_seconds = None
    with torch.inference_mode():
        for name, fused in paths.items():
            t0 = time.perf_counter()
            triangulate_rays(o, d, w, fused=fused)  # warm-up (allocator, thread pool, compilation)
            if fused:
                compile_seconds = time.perf_counter() - t0
            times[name] = []
        for _ in range(args.repeats):  # interleaved, so that a busy spell on a shared machine hits both
            for name, fused in paths.items():
                t0 = time.perf_counter()
                X_hat, valid = triangulate_rays(o, d, w, fused=fused)
                times[name].append(time.perf_counter() - t0)
                errors[name] = (X_hat.double() - X).norm(dim=-1).max().item()
                if not valid.all():
                    raise RuntimeError(f"{name}: {int((~valid).sum())} noise-free points flagged invalid")
    rates = {name: args.points / min(t) for name, t in times.items()}
    best_path = max(rates, key=rates.__getitem__)
    best = min(times[best_path])

    m = min(args.cv_points, args.points)
    o64, d64, w64 = (t[:m].double().numpy() for t in (o, d, w))
    X_cv, cv_seconds = opencv_loop(o64, d64, w64)
    err_cv = np.linalg.norm(X_cv - X[:m].numpy(), axis=-1)
    X_ours64, _ = triangulate_rays(*(torch.from_numpy(a) for a in (o64, d64, w64)))
    diff_cv = np.abs(X_ours64.numpy() - X_cv).max()

    flops = matmul_flops(seconds=args.matmul_seconds)
    solves = rates[best_path]
    cv_solves = m / cv_seconds
    print(f"{args.points} points x {args.views} views, {args.dtype}, {torch.get_num_threads()} threads:")
    for name, t in times.items():
        print(
            f"  {name:>5}: best {min(t) * 1e3:.1f} ms (median {statistics.median(t) * 1e3:.1f} ms) -> "
            f"{rates[name] / 1e6:.1f} M solves/s; max error {errors[name]:.2e} m"
        )
    if compile_seconds is not None:
        print(f"  fused: first call (compilation) {compile_seconds:.1f} s")
    print(f"best: {best_path}, {solves / 1e6:.1f} M solves/s (target {TARGET / 1e6:.0f} M)")
    print(
        f"OpenCV per-point loop ({m} points, float64): {cv_solves / 1e3:.1f} k solves/s, "
        f"max error {err_cv.max():.2e} m, max |ours(float64) - OpenCV| {diff_cv:.2e} m; "
        f"batched/loop speed-up {solves / cv_solves:.0f}x; matmul {flops / 1e9:.1f} GFLOP/s"
    )
    emit(
        {
            "benchmark": "triangulation",
            "solves_per_s": solves,
            "opencv_loop_solves_per_s": cv_solves,
            "speedup_vs_opencv_loop": solves / cv_solves,
            "target_solves_per_s": TARGET,
            "meets_target": solves >= TARGET,
            "points": args.points,
            "views": args.views,
            "dtype": args.dtype,
            "best_path": best_path,
            "solves_per_s_eager": rates["eager"],
            "solves_per_s_fused": rates.get("fused"),
            "fused_first_call_s": compile_seconds,
            "seconds_best": best,
            "seconds_median": statistics.median(times[best_path]),
            "repeats": args.repeats,
            "max_error_m": max(errors.values()),
            "opencv_loop_points": m,
            "opencv_max_error_m": float(err_cv.max()),
            "max_abs_diff_vs_opencv_m": float(diff_cv),
            "matmul_flops": flops,
            "machine": machine_info(),
        }
    )
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        sys.exit(main())
