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

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.experiments.accuracy import without_notes  # noqa: E402
from s3k.experiments.grid import LABEL_CHOICES  # noqa: E402
from s3k.experiments.poses import label_poses  # noqa: E402


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
    report = label_poses(args.pools, args.choices, args.labelled, args.seed)
    result = {
        "command": shlex.join(["python", "benchmarks/label_poses.py",
                               *without_notes(sys.argv[1:] if argv is None else argv)]),
        "git_revision": git_revision(),
        "machine": machine_info(),
        **report,
    }
    write_and_emit(result, args.out)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
