"""Coarse-to-fine on the box scene: a coarse pass on the whole image, a refining pass on crops around it.

The coarse detector trains on the whole image resized to ``--coarse-size`` px (S3K, as ``s3k demo``); its
3D estimates of every frame (labelled, unlabelled and test: the same rule at training and at test) centre one
crop of the whole object per view, ``--extent-mm`` wide at the estimate's depth, cut from the
``--render`` px images and resampled to ``--crop`` px (:func:`s3k.data.crops.write_crop_dataset`). The
refining detector trains on those crops with and without the self-supervised term, and is evaluated on the
test
frames' crops: its triangulated points are the two-pass detector's 3D keypoints. Both refining models use the
same crops (from the S3K coarse pass), so the comparison isolates the refining pass.

Example::

    python benchmarks/two_pass.py --work runs/two-pass     # about 1.5 CPU-hours on 2 cores

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import crop_figures, ensure_box_render, finish, git_revision, train_side_by_side  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", default=str(ROOT / "runs" / "two-pass"), help="working folder")
    p.add_argument("--render", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--unlabelled", type=int, default=2000, help="unlabelled frames (default 2000)")
    p.add_argument("--test", type=int, default=200, help="test frames (default 200)")
    p.add_argument("--coarse-size", type=int, default=96, help="coarse pass image size (default 96)")
    p.add_argument("--coarse-steps", type=int, default=4000, help="coarse training steps (default 4000)")
    p.add_argument("--extent-mm", type=float, default=250.0, help="crop side at the estimate (default 250)")
    p.add_argument("--crop", type=int, default=128, help="crop size in pixels (default 128)")
    p.add_argument("--steps", type=int, default=4000, help="refining training steps (default 4000)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    revision = git_revision()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    render = ensure_box_render(work, args.render, args.unlabelled, args.test)
    coarse = work / f"coarse-{args.coarse_size}px-{args.coarse_steps}-s{args.seed}"
    from s3k.config import TrainConfig

    train_side_by_side({"coarse": (render, coarse, TrainConfig.from_flat(
        image_size=args.coarse_size, steps=args.coarse_steps, seed=args.seed))})
    estimates = work / f"{coarse.name}.csv"
    if not estimates.is_file():
        subprocess.run([sys.executable, "-m", "s3k.cli", "predict", str(coarse), "--data", str(render),
                        "--split", "all", "--out", str(estimates)], check=True, stdout=subprocess.DEVNULL)
    view = work / f"crops-{coarse.name}-{args.extent_mm:g}mm-{args.crop}px"
    from s3k.data import Dataset
    from s3k.data.crops import object_centres, write_crop_dataset
    from s3k.data.tracks_csv import read_csv

    keypoints = Dataset.open(render, cache="none").keypoints
    centres = object_centres(read_csv(estimates, keypoints))
    if not (view / "s3k.json").is_file():
        # a frame the coarse pass could not triangulate is cropped around the workspace centre
        write_crop_dataset(render, view, centres, args.extent_mm / 1000, args.crop,
                           fallback=True, overwrite=True,
                           description=f"crops of {args.extent_mm:g} mm around {coarse.name}'s estimates")
    fine = {name: work / f"{view.name}-{name}-{args.steps}-s{args.seed}" for name in ("labels_only", "s3k")}
    train_side_by_side({name: (view, run, TrainConfig.from_flat(steps=args.steps, seed=args.seed,
                                                                unsup=name != "labels_only"))
                        for name, run in fine.items()})
    from s3k.inference.evaluate import evaluate_run

    scale = (f"box rendered at {args.render} px; coarse S3K at {args.coarse_size} px, {args.coarse_steps} "
             f"steps; object crops {args.extent_mm:g} mm -> {args.crop} px; refining {args.steps} steps")
    result: dict = {"benchmark": "two_pass", "command": shlex.join(["python", *sys.argv]),
                    "git_revision": revision, "scale": scale,
                    "coarse_estimates": len(centres)}
    coarse_test = evaluate_run(coarse, render, split="test", device="cpu")
    result["coarse_s3k"] = {"test": crop_figures(coarse_test)[0]}
    for name, run in fine.items():
        figures, per_keypoint = crop_figures(evaluate_run(run, view, split="test", device="cpu"))
        result[name] = {"test": figures, "median_mm_per_keypoint": per_keypoint}
    finish(result, t0, args.out)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
