"""How precise a refining pass on scale-normalized crops can be, given a coarse 3D estimate.

A diagnostic for the error budget of the coarse-to-fine detector (docs/accuracy-log.md, 2026-12-01). It
renders the box scene at ``--render`` px, and for one keypoint (or, with ``--keypoint -1``, the whole object)
writes a dataset whose "cameras" are crops: each view cut around the keypoint's *true* 3D position (the
object's: the mean of its keypoints) plus a random 3D offset (``--jitter-mm`` per axis, standing in for
the coarse pass's error), sized from a metric extent (``--extent-mm``) and resampled to ``--crop`` px with
``K' = M K`` (:mod:`s3k.geometry.warp`). It trains the labels-only baseline and S3K on it (same steps, same
seed) and
reports the keypoint's 3D error on the test frames and on the labelled frames (the fit).

Because the crop centre comes from the ground truth, the figure is what the refining pass adds when the
coarse pass is within the jitter; a real coarse pass has outliers too.

Example::

    python benchmarks/oracle_crops.py --work runs/oracle-crops            # about 1 CPU-hour on 2 cores
    python benchmarks/oracle_crops.py --work runs/oracle-crops --steps 8000

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import crop_figures, ensure_box_render, finish, git_revision, train_side_by_side  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def write_crop_view(source: Path, out: Path, keypoint: int, extent_m: float, size: int, jitter_m: float,
                    seed: int = 123) -> None:
    """The crop dataset of one keypoint (its only keypoint), crops centred on the jittered true point; with
    ``keypoint < 0`` of every keypoint, crops centred on the jittered mean of the true points."""
    from s3k.data import Dataset
    from s3k.data.crops import write_crop_dataset

    ds = Dataset.open(source, cache="none")
    rng = np.random.default_rng(seed)
    kps = slice(None) if keypoint < 0 else slice(keypoint, keypoint + 1)
    centres = {}
    for split in ("labelled", "unlabelled", "test"):
        ids = ds.frames(split)
        X, _ = ds.points3d(ids)
        truth = X[:, kps].mean(axis=1)
        for frame, c, offset in zip(ids, truth, rng.normal(0.0, jitter_m, (len(ids), 3))):
            centres[int(frame)] = c + offset
    name = "the object" if keypoint < 0 else ds.keypoints[keypoint]
    write_crop_dataset(source, out, centres, extent_m, size, ds.keypoints[kps],
                       description=f"crops of {extent_m * 1000:g} mm around {name} (true point + jitter)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", default=str(ROOT / "runs" / "oracle-crops"), help="working folder")
    p.add_argument("--render", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--unlabelled", type=int, default=2000, help="unlabelled frames (default 2000)")
    p.add_argument("--test", type=int, default=200, help="test frames (default 200)")
    p.add_argument("--keypoint", type=int, default=0,
                   help="keypoint index (default 0); -1: crops of the whole object, every keypoint")
    p.add_argument("--extent-mm", type=float, default=80.0, help="crop side at the point (default 80)")
    p.add_argument("--crop", type=int, default=64, help="crop size in pixels (default 64)")
    p.add_argument("--jitter-mm", type=float, default=8.0, help="crop centre offset per axis, sd (default 8)")
    p.add_argument("--steps", type=int, default=4000, help="training steps per model (default 4000)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--s3k-options", default="",
                   help="more 's3k train' options for the S3K model, e.g. '--outlier-px 6 --alpha 0.25'")
    p.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    revision = git_revision()  # the code that trains, read before anything else changes the checkout
    render = ensure_box_render(work, args.render, args.unlabelled, args.test)
    which = "all" if args.keypoint < 0 else args.keypoint
    view = work / f"crops-k{which}-{args.extent_mm:g}mm-{args.crop}px-j{args.jitter_mm:g}"
    if not (view / "s3k.json").is_file():
        write_crop_view(render, view, args.keypoint, args.extent_mm / 1000, args.crop, args.jitter_mm / 1000)
    extra_s3k = args.s3k_options.split()
    tag = "".join(o.lstrip("-").replace("-", "") for o in extra_s3k)
    models = {"labels_only": ["--no-unsup"], "s3k": extra_s3k}
    suffix = {"labels_only": "", "s3k": tag}
    runs = {name: work / "runs" / f"{view.name}-{name}{suffix[name]}-{args.steps}-s{args.seed}"
            for name in models}
    from s3k.config import TrainConfig

    base = TrainConfig.from_flat(steps=args.steps, seed=args.seed)
    train_side_by_side({name: (view, runs[name], base.with_options(extra, where="--s3k-options"))
                        for name, extra in models.items()})
    from s3k.inference.evaluate import evaluate_run

    result: dict = {"benchmark": "oracle_crops", "command": shlex.join(["python", *sys.argv]),
                    "git_revision": revision,
                    "scale": f"box rendered at {args.render} px, crops {args.extent_mm:g} mm -> {args.crop} "
                             f"px, centre jitter {args.jitter_mm:g} mm per axis, {args.steps} steps",
                    "keypoint": args.keypoint}
    result["s3k_options"] = args.s3k_options
    for name in models:
        run = runs[name]
        result[name] = {}
        for split in ("test", "labelled"):
            figures, per_keypoint = crop_figures(evaluate_run(run, view, split=split, device="cpu"))
            result[name][split] = {**figures, "median_mm_per_keypoint": per_keypoint}
    finish(result, t0, args.out)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
