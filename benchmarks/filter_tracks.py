"""Filtering over time against the truth: a trained box detector tracks a rendered trajectory of the box
(``s3k.sim.trajectory``: a fixed 4-camera rig, the box sliding and turning on the table, H.264 videos) as
``s3k track`` does (raw points, and the offline Kalman/RTS filter) and as ``s3k stream --filter kalman``
does (the causal filter), and each is compared with the true keypoints
(:func:`s3k.experiments.track_filter.filter_benchmark`): 3D error median and RMS in mm, the causal filter's
delay in frames and the frame-to-frame jitter.

The detector: any box run; the committed figures use a one-pass run at 96 px
(``s3k simulate box --out D --size 96 --labelled 10 --unlabelled 1000 --test 20`` then ``s3k train D --out RUN
--steps 3000 --threads 1 --layout-tol 0.1``).

Example::

    python benchmarks/filter_tracks.py RUN --work /tmp/filter-work --out docs/results/tracks/box-filter.json
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, write_and_emit  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="a box detector's run folder")
    p.add_argument("--work", required=True, help="folder for the rendered videos and the tracks")
    p.add_argument("--frames", type=int, default=300, help="frames of the trajectory (default 300: 10 s)")
    p.add_argument("--size", type=int, default=96, help="image size of the videos (default 96)")
    p.add_argument("--seed", type=int, default=0, help="draws the rig, the lighting and the path (default 0)")
    p.add_argument("--out", default=None, help="JSON file to write")
    a = p.parse_args(argv)
    import torch

    from s3k.experiments.track_filter import filter_benchmark

    torch.set_num_threads(1)
    result = filter_benchmark(a.run, a.work, a.frames, a.size, a.seed)
    given = sys.argv[1:] if argv is None else argv
    result = {"command": "python benchmarks/filter_tracks.py " + shlex.join(given),
              "revision": git_revision(), "run": a.run, **result}
    for what in ("raw", "offline", "causal"):
        r = result[what]
        print(f"{what:8s} median {r['median']:.2f} mm  RMS {r['rms']:.2f} mm  ({r['points']} points)")
    print(f"causal delay {result['causal_delay_frames']} frame(s); jitter (median |second difference|, mm): "
          + ", ".join(f"{k} {v:.3f}" for k, v in result["jitter_mm_per_frame2"].items()))
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
