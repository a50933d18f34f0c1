"""The real recording's tracks over seeds: the per-seed results of ``benchmarks/real_tracks.py --loop
--control`` (one S3K run per seed) side by side, with the mean over seeds and its 95% t-interval of:

- the filtered minus the raw points' 3D error on the test frames (median and RMS, mm; each seed's own
  bootstrap interval is in its file) and the jitter of both;
- one round of the way back: after minus before, and after minus the control (as many steps without the
  new labels), on the test frames, raw points (median, RMS and 90th percentile: the loop adds the frames
  the track doubted most, so its gain is expected in the large errors);
- where the per-seed files hold ``--repeats`` fine-tunings: each seed's mean over its repeats of those
  differences, and over seeds the mean of those means with its 95% t-interval (``repeats``).

Example (after ``bash scripts/real-tracks.sh``, which writes the per-seed files)::

    python benchmarks/real_tracks_seeds.py docs/results/tracks/real-seed*.json \\
        --out docs/results/tracks/real-seeds.json
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, t_interval, write_and_emit  # noqa: E402

FIGURES = {
    "filtered_minus_raw_median_mm": ("before", "filtered_minus_raw_test", "median"),
    "filtered_minus_raw_rms_mm": ("before", "filtered_minus_raw_test", "rms"),
    "loop_after_minus_before_median_mm": ("loop", "after_minus_before_test", "raw", "median"),
    "loop_after_minus_before_rms_mm": ("loop", "after_minus_before_test", "raw", "rms"),
    "loop_after_minus_control_median_mm": ("loop", "after_minus_continued_test", "raw", "median"),
    "loop_after_minus_control_rms_mm": ("loop", "after_minus_continued_test", "raw", "rms"),
    "loop_after_minus_before_p90_mm": ("loop", "after_minus_before_test", "raw", "p90"),
    "loop_after_minus_control_p90_mm": ("loop", "after_minus_continued_test", "raw", "p90"),
}


def dig(d: dict, path: tuple[str, ...]):
    for k in path:
        d = d[k]
    return d


def per_seed(result: dict) -> dict:
    out = {name: dig(result, path) for name, path in FIGURES.items()}
    for name, path in FIGURES.items():
        ci = dig(result, path[:-1]).get(path[-1] + "_ci95")
        out[name.replace("_mm", "_ci95_mm")] = ci
    before = result["before"]
    out["raw_test_median_mm"] = before["raw"]["test"]["median"]
    out["raw_test_rms_mm"] = before["raw"]["test"]["rms"]
    out["jitter_raw_mm_per_frame2"] = before["raw"]["jitter_mm_per_frame2"]
    out["jitter_filtered_mm_per_frame2"] = before["filtered"]["jitter_mm_per_frame2"]
    out["jitter_reference_mm_per_frame2"] = result.get("reference_jitter_mm_per_frame2")
    out["reference"] = result.get("reference")
    spread = "reference_without_one_camera_test_median_mm"
    out[spread] = result.get(spread)
    out["loop_lr"] = result["loop"]["lr"]
    out["loop_steps"] = result["loop"]["steps"]
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+",
                   help="per-seed JSON files of benchmarks/real_tracks.py --loop --control")
    p.add_argument("--out", default=None, help="JSON file to write")
    a = p.parse_args(argv)
    seeds = {}
    for path in a.results:
        result = json.loads(Path(path).read_text())
        seeds[Path(path).name] = {"run": result["run"], "revision": result["revision"], **per_seed(result)}
    over: dict = {}
    for name in [*FIGURES, "jitter_raw_mm_per_frame2", "jitter_filtered_mm_per_frame2"]:
        values = [s[name] for s in seeds.values()]
        over[name] = {"mean": sum(values) / len(values), "ci95": t_interval(values),
                      "per_seed": values}
        print(f"{name:38s} mean {over[name]['mean']:+.3f}  per seed "
              + " ".join(f"{v:+.3f}" for v in values))
    repeated = repeats_over_seeds([json.loads(Path(path).read_text()) for path in a.results])
    given = sys.argv[1:] if argv is None else argv
    write_and_emit({"command": "python benchmarks/real_tracks_seeds.py " + shlex.join(given),
                    "revision": git_revision(), "seeds": seeds, "over_seeds": over,
                    **({"repeats": repeated} if repeated else {})}, a.out)


def repeats_over_seeds(results: list[dict]) -> dict:
    """Over the seeds whose loop was repeated (``real_tracks.py --repeats``): per figure the seeds' means over
    their repeats, the mean of those and its 95% t-interval, and the repeats per seed; {} if none was."""
    over = [r["loop"]["repeats"]["over_repeats"] for r in results if "repeats" in r.get("loop", {})]
    if not over:
        return {}
    KEYPOINTS = "after_minus_control_median_per_keypoint_mm"
    out: dict = {"seeds": len(over),
                 "repeats_per_seed": [len(o["after_minus_before_median_mm"]["per_repeat"]) for o in over]}
    for name in over[0]:
        if name == KEYPOINTS:
            continue
        means = [o[name]["mean"] for o in over if name in o]
        out[name] = {"mean": sum(means) / len(means), "ci95": t_interval(means), "per_seed_mean": means}
        print(f"repeated {name:34s} mean {out[name]['mean']:+.3f}  per seed "
              + " ".join(f"{v:+.3f}" for v in means))
    per_keypoint = [o[KEYPOINTS] for o in over if KEYPOINTS in o]
    if per_keypoint:  # each keypoint's mean over seeds of the seeds' means over repeats
        out[KEYPOINTS] = {k: {"mean": sum(d[k] for d in per_keypoint) / len(per_keypoint),
                              "per_seed_mean": [d[k] for d in per_keypoint]} for k in per_keypoint[0]}
        print("repeated after minus control, test median per keypoint (mm): " + ", ".join(
            f"{k} {v['mean']:+.2f}" for k, v in out[KEYPOINTS].items()))
    return out


if __name__ == "__main__":
    main()
