"""Accuracy on the box scene: S3K against the labels-only baseline on the same labels.

Targets: docs/method.md#performance-targets.

Renders the box scene (10 labelled frames, thousands of unlabelled ones, a test set), trains the network
with and without the self-supervised term (same seed, same labelled batches, same augmentation), evaluates
both on the same test frames and writes ``docs/results/accuracy/accuracy.json`` and ``accuracy.png`` with the
command, the git revision, the scale and the machine. The targets: median 3D error <= 3 mm, RMS <= 6 mm
and at most 0.6 times the baseline's, 95% of keypoints within 10 mm; the figures are stated at this scale
(96 px, thousands of steps), not the paper's (400 px, 150k steps).

The work is done by ``s3k.demo.run_demo`` in ``--work`` (default ``runs/accuracy``), each stage skipped when
its output exists: pointing ``--work`` at a finished ``s3k demo --out DIR`` with the same sizes reuses it.

Example::

    python benchmarks/accuracy.py                # 15-25 minutes on a 2-core CPU
    python benchmarks/accuracy.py --steps 6000   # longer training

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision, machine_info  # noqa: E402
from s3k.demo import DemoConfig, comparison_table, run_demo, schedule_for  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("rms_px", "rms_px_reproj", "median_mm", "rms_mm", "pck_5mm", "pck_10mm", "mm_per_px")


def main(argv: list[str] | None = None) -> int:
    d = DemoConfig()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", default=str(ROOT / "runs" / "accuracy"), help="working folder")
    parser.add_argument("--results", default=str(ROOT / "docs" / "results" / "accuracy"),
                        help="where the JSON and the plot go")
    parser.add_argument("--size", type=int, default=d.size, help=f"image size (default {d.size})")
    parser.add_argument("--unlabelled", type=int, default=d.unlabelled,
                        help=f"unlabelled frames (default {d.unlabelled})")
    parser.add_argument("--test", type=int, default=d.test, help=f"test frames (default {d.test})")
    parser.add_argument("--steps", type=int, default=d.steps, help=f"steps per model (default {d.steps})")
    parser.add_argument("--warmup-steps", type=int, default=None,
                        help=f"S3K warm-up (default {d.warmup_steps}, or steps / 4 when shorter)")
    parser.add_argument("--alpha", type=float, default=d.alpha, help=f"S3K alpha (default {d.alpha})")
    parser.add_argument("--seed", type=int, default=d.seed)
    parser.add_argument("--sequential", action="store_true", help="train one model after the other")
    args = parser.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    sched = schedule_for(args.steps)
    if args.warmup_steps is not None:
        sched["warmup_steps"] = args.warmup_steps
    demo = DemoConfig(size=args.size, labelled=d.labelled, unlabelled=args.unlabelled, test=args.test,
                      steps=args.steps, alpha=args.alpha, seed=args.seed, **sched)
    t0 = time.perf_counter()
    summary = run_demo(args.work, demo, progress=False, parallel=not args.sequential,
                       log=lambda m: print(m, file=sys.stderr, flush=True))
    minutes = (time.perf_counter() - t0) / 60
    runs = {"s3k": summary["S3K"], "baseline": summary["labels only"]}
    result = {
        "benchmark": "accuracy",
        "scene": "box",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "git_revision": git_revision(),
        "scale": summary["scale"],
        "config": asdict(demo),
        "minutes_this_call": minutes,
        "timings_s": summary["timings"],
        "stages_run_in_this_call": summary["stages_run_in_this_call"],
        **{name: {k: m[k] for k in KEYS} for name, m in runs.items()},
        "per_keypoint": {name: m["per_keypoint"] for name, m in runs.items()},
        "median_mm_ratio": (runs["s3k"]["median_mm"] / runs["baseline"]["median_mm"]
                            if runs["baseline"]["median_mm"] else None),
        "targets": {"median_mm_at_most": 3.0, "rms_mm_at_most": 6.0, "rms_mm_ratio_at_most": 0.6,
                    "pck_10mm_at_least": 0.95},
        "machine": machine_info(),
    }
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    (out / "accuracy.json").write_text(json.dumps(result, indent=2, default=str) + "\n")
    shutil.copyfile(Path(args.work) / "report" / "comparison.png", out / "accuracy.png")
    print(comparison_table({"labels only": runs["baseline"], "S3K": runs["s3k"]}), file=sys.stderr)
    emit({k: v for k, v in result.items() if k != "per_keypoint"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
