"""Where a two-pass frame's CPU time goes: ``benchmarks/inference.py``'s ``two_pass`` pipeline (fast path,
untrained networks, 4 views of noise at ``--native`` px), one frame at a time, each part timed by wrapping
it: the networks (``net``), cutting their inputs (``cut``: the coarse resize and the refining crops), the
read-out of both passes (``readout``: heatmap -> 2D -> weighted triangulation -> 3D), the crop centres,
boxes and pixel maps. Milliseconds per frame, mean over ``--frames`` frames after warm-up; the last line is
one JSON object with the machine.

The s3k on ``PYTHONPATH`` comes first (this file's checkout only after it), so the same script times another
revision's code: ``PYTHONPATH=/path/to/other/checkout python benchmarks/two_pass_parts.py``.

Example::

    python benchmarks/two_pass_parts.py --threads 1
"""

from __future__ import annotations

import argparse
import collections
import os
import shlex
import sys
import time

import torch

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--frames", type=int, default=200, help="timed frames (default 200)")
    args = p.parse_args(argv)

    import s3k
    import s3k.detector.detector as D
    from benchmarks import inference

    bench = ["--size", "128", "--native", "384", "--coarse", "96", "--crop", "192", "--batch", "1",
             "--threads", str(args.threads)]
    q = argparse.ArgumentParser()
    inference.add_network_options(q, "")
    for name, default in (("--native", 384), ("--coarse", 96), ("--crop", 192), ("--batch", 1)):
        q.add_argument(name, type=int, default=default)
    q.add_argument("--precision", default="float32")
    q.add_argument("--outlier-px", type=float, default=inference.TrainConfig().self_supervision.outlier_px)
    q.add_argument("--compile", action="store_true")
    detector, frames, cams = inference.detectors(q.parse_args(bench), torch.device("cpu"))["two_pass"]

    spent: dict[str, float] = collections.defaultdict(float)

    def timed(owner, name: str, part: str) -> None:
        inner = getattr(owner, name)

        def wrapper(*a, **k):
            t0 = time.perf_counter()
            out = inner(*a, **k)
            spent[part] += time.perf_counter() - t0
            return out

        setattr(owner, name, wrapper)

    for owner, name, part in ((D._Pass, "cut", "cut"), (D._Pass, "logits", "net"), (D, "read_out", "readout"),
                              (D, "crop_centres", "crop_centres"), (D, "metric_crop_boxes", "crop_boxes"),
                              (D, "crop_maps", "pixel_maps")):
        timed(owner, name, part)
    frame = frames[0]
    for _ in range(20):
        detector(frame, cams)
    spent.clear()
    t0 = time.perf_counter()
    for _ in range(args.frames):
        detector(frame, cams)
    total = (time.perf_counter() - t0) / args.frames * 1e3
    parts = {k: v / args.frames * 1e3 for k, v in spent.items()}
    parts["rest"] = total - sum(parts.values())
    print(f"two_pass {total:.2f} ms per frame: " + ", ".join(f"{k} {v:.2f}" for k, v in parts.items()))
    emit({"command": shlex.join(["python", "benchmarks/two_pass_parts.py", *(sys.argv[1:] if argv is None
                                                                             else argv)]),
          "benchmark": "two_pass_parts", "s3k": os.path.dirname(os.path.dirname(s3k.__file__)),
          "git_revision": git_revision(), "threads": args.threads, "frames": args.frames,
          "ms_per_frame": total, "parts_ms_per_frame": parts})
    return 0


if __name__ == "__main__":
    sys.exit(main())
