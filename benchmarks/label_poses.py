"""Which resting poses ten labelled frames show, for each way of choosing them, without training anything.

For each rendered POOL (a dataset with many labelled frames and their true 3D points, as
``benchmarks/accuracy.py --label-pool N`` renders) and each ``--choices`` entry, the frames that
``benchmarks/accuracy.py --label-choice CHOICE`` would train on (:func:`s3k.experiments.views.select_frames`
with the pool's own sampling seed) are counted by pose, as ``benchmarks/error_by_pose.py`` names them: lid
up, lid down, on a side with the edge from keypoint 0 to 1 level (the box on a long edge) or upright (on an
end). ``missing`` counts, per choice, the pools where some pose that the test frames show has no label: the
pose a detector then has to guess.

Prints one JSON line and writes it to ``--out``.

Example::

    python benchmarks/label_poses.py runs/accuracy-box-representative/box384-L100-seed{0,1,2} \\
        --out docs/results/accuracy/label-poses.json
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, without_notes, write_and_emit  # noqa: E402
from benchmarks.error_by_pose import pose_counts  # noqa: E402
from s3k.experiments.grid import LABEL_CHOICES  # noqa: E402


def true_poses(pool, split: str) -> np.ndarray:
    """``(B, K, 3)`` true 3D keypoints of a split's frames, NaN where not known."""
    points = pool.points3d(pool.frames(split))
    if points is None:
        raise SystemExit(f"{pool.path}: no 3D points; label_poses needs a rendered pool")
    return np.where(points[1][..., None], points[0], np.nan)


def pool_report(path: Path, choices: list[str], labelled: int, seed: int | None) -> dict:
    from s3k.data import Dataset
    from s3k.experiments.views import select_frames

    pool = Dataset.open(path, cache="none")
    if seed is None:
        seed = (pool.source or {}).get("seed")
        if seed is None:
            raise SystemExit(f"{path}: s3k.json records no sampling seed; pass --seed")
    ids = pool.frames("labelled")
    if len(ids) < labelled:
        raise SystemExit(f"{path}: {len(ids)} labelled frames, fewer than --labelled {labelled}")
    poses = true_poses(pool, "labelled")
    test = pose_counts(true_poses(pool, "test"))
    labels = {}
    for choice in choices:
        picked = select_frames(pool, labelled, len(pool.frames("unlabelled")), int(seed), choice=choice)
        labels[choice] = pose_counts(poses[np.searchsorted(ids, picked["labelled"])])
    unlabelled = {c: [p for p, n in test.items() if n and not got[p]] for c, got in labels.items()}
    return {"pool": str(path), "seed": int(seed), "pool_poses": pose_counts(poses), "test_poses": test,
            "labels": labels, "unlabelled_poses": unlabelled}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("pools", nargs="+", metavar="POOL", help="rendered datasets with many labelled frames")
    p.add_argument("--choices", nargs="+", choices=LABEL_CHOICES, default=list(LABEL_CHOICES),
                   help="ways of choosing the labelled frames (default: all)")
    p.add_argument("--labelled", type=int, default=10, help="labelled frames chosen (default 10)")
    p.add_argument("--seed", type=int, default=None,
                   help="choice seed for every pool (default: each pool's own sampling seed, as "
                        "benchmarks/accuracy.py uses)")
    p.add_argument("--out", default=None, help="also write the JSON here")
    args = p.parse_args(argv)
    for path in args.pools:
        if not (Path(path) / "s3k.json").is_file():
            raise SystemExit(f"{path}: not a dataset folder (no s3k.json)")
    pools = [pool_report(Path(path), args.choices, args.labelled, args.seed) for path in args.pools]
    result = {
        "command": shlex.join(["python", "benchmarks/label_poses.py",
                               *without_notes(sys.argv[1:] if argv is None else argv)]),
        "git_revision": git_revision(),
        "machine": machine_info(),
        "labelled": args.labelled,
        "pools": pools,
        "missing": {c: sum(bool(r["unlabelled_poses"][c]) for r in pools) for c in args.choices},
    }
    write_and_emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
