"""Dataset generation speed: `s3k simulate` end to end (worker start-up, rendering, labels, PNGs on disk).

    python benchmarks/render.py --size 128            # box scene, 400 frames = 1600 images
    python benchmarks/render.py --scene distractors --frames 200

Prints a line per measurement and, last, one JSON line whose ``images_per_s`` is the end-to-end figure (the
target is >= 200 images/s at 128 px on a 2-core machine). ``render_only_images_per_s`` is one process
rendering and labelling frames in memory, for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from s3k.cli import showing_library_messages  # noqa: E402
from s3k.sim.generate import SimulateConfig, default_workers, frame_plan, frame_rng, simulate  # noqa: E402
from s3k.sim.scenes import make_scene  # noqa: E402


def _emit(result: dict) -> None:
    """The shared `benchmarks.common.emit` (imported here, not at the top: rendering workers are spawned and
    re-import this file, and should not load torch)."""
    try:
        from benchmarks.common import emit, machine_info
    except ImportError:  # pragma: no cover - the shared helpers are missing
        result["machine"] = {"platform": platform.platform(), "cpus": default_workers(),
                             "load_avg_1min": round(os.getloadavg()[0], 2)}
        print(json.dumps(result), flush=True)
        return
    result["machine"] = {**machine_info(), "mujoco_gl": os.environ.get("MUJOCO_GL")}
    emit(result)


def render_only(scene: str, size: int, frames: int) -> float:
    """Images per second of one process rendering and labelling frames, nothing written."""
    cfg = SimulateConfig(scene, size=size, labelled=0, unlabelled=frames, test=0)
    specs = frame_plan(cfg)
    with make_scene(scene, size=size, seed=0) as s:
        s.frame(specs[0], frame_rng(0, 0))  # the first frame creates the OpenGL context
        t = time.perf_counter()
        for spec in specs:
            s.frame(spec, frame_rng(0, spec.frame_id))
        return len(specs) * s.num_cameras / (time.perf_counter() - t)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="box", choices=["box", "distractors", "category"])
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--frames", type=int, default=400, help="frames to write (4 images each)")
    p.add_argument("--workers", type=int, default=None, help="rendering processes (default: CPUs available)")
    args = p.parse_args()

    single = render_only(args.scene, args.size, min(100, args.frames))
    print(f"render only, 1 process: {single:.0f} images/s")
    cfg = SimulateConfig(args.scene, size=args.size, labelled=min(10, args.frames),
                         unlabelled=max(0, args.frames - 10), test=0, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        out = simulate(cfg, Path(tmp) / "ds", workers=args.workers, progress=False)
        size_mb = sum(f.stat().st_size for f in (Path(tmp) / "ds").rglob("*") if f.is_file()) / 2**20
    print(f"end to end: {out['images']} images in {out['seconds']:.2f} s = {out['images_per_s']:.0f} "
          f"images/s ({size_mb:.1f} MB on disk)")
    _emit({
        "benchmark": "render",
        "scene": args.scene,
        "size": args.size,
        "frames": out["frames"],
        "images": out["images"],
        "workers": args.workers or default_workers(),
        "seconds": round(out["seconds"], 3),
        "images_per_s": round(out["images_per_s"], 1),
        "render_only_images_per_s": round(single, 1),
        "target_images_per_s": 200,
    })


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        main()
