"""Where a detector's 3D error comes from, by the object's pose: the test frames grouped by which way the
plane of the first three keypoints faces (its normal up, down, or on a side: more than 45 degrees from the
world's vertical); the frames where the keypoints are detected drawn together (their mean pairwise distance
below half the true one: a collapse, whatever the confidence says), and the frames where a keypoint is
detected nearer another keypoint's true place than its own (swapped: a symmetric confusion;
``nearest_true`` counts, per keypoint, which true keypoint its detections lie nearest). Within each pose,
the error's constant part: each keypoint's mean error in the frame of the true keypoints (x from
keypoint 0 to 1, y from keypoint 2 to 1, z their normal), ``bias_mm``, and the median once it is taken away,
``median_mm_without_bias`` - what better precision alone could reach, and what a systematic lean costs. The
poses on a side are split once more, ``by_edge``, by whether the edge from keypoint 0 to 1 is level or
upright (on the box: standing on a long edge or on an end); ``labelled_poses`` counts the DATA's labelled
frames the same way.

Each RUN is read with its DATA (a two-pass run with its full-resolution dataset, or any run with the dataset
it reads, e.g. a refining pass with its crops). Prints one JSON line and writes it to ``--out``.

Example::

    python benchmarks/error_by_pose.py runs/accuracy-box/s3k-seed2 runs/accuracy-box/box384-seed2 \\
        runs/accuracy-box/labels_only-seed2 runs/accuracy-box/box384-seed2 --out by-pose.json
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import add_run_data_arguments, run_data_pairs, write_runs  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.experiments.poses import by_pose, labelled_poses, predictions  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_run_data_arguments(p)
    args = p.parse_args(argv)
    pairs = run_data_pairs(p, args)
    import torch

    torch.set_num_threads(1)
    runs = {}
    for run, data in pairs:
        pred, truth, mm = predictions(Path(run), Path(data), args.split)
        runs[run] = {"data": data, "labelled_poses": labelled_poses(Path(data)), **by_pose(pred, truth, mm)}
        a = runs[run]
        poses = "; ".join(f"{k} {v.get('median_mm', np.nan):.1f}/{v.get('rms_mm', np.nan):.1f} mm "
                          f"({v['frames']} frames)" for k, v in a["by_pose"].items())
        print(f"{run}: median {a['all']['median_mm']:.2f} mm, RMS {a['all']['rms_mm']:.1f} mm; collapsed "
              f"{a['collapsed_frames']}/{a['frames']} frames ("
              f"{100 * a['collapsed'].get('share_of_squared_error', 0):.0f}% of the squared error), swapped "
              f"{a['swapped_frames']} ({100 * a['swapped'].get('share_of_squared_error', 0):.0f}%); {poses}",
              file=sys.stderr)
    write_runs("benchmarks/error_by_pose.py", argv, args, runs)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
