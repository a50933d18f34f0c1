"""Two models over seeds on cameras outside the training rig: ``benchmarks/outside_rig.py --diagnose`` results
of each model's seeds, side by side on the same test sets.

Per model and rig, seed by seed and as a mean over seeds: the median 3D error and its ratio to the in-range
(``train``) set's, and the refining pass's median 2D error and its ratio to the in-range one. Per rig, the
first model's median minus the second's, in 3D (mm) and 2D (px), seed by seed, and in how many seeds the first
is lower. The files of one model are its seeds in order, and each seed's two files must read the same test
sets (scene, size, frames, sampling seed and rigs), or the call is refused naming the file.

Example (the encoder's and the scratch U-Net's 20-label S3K models of the label curve, seeds 0-2)::

    for s in 0 1 2; do python benchmarks/outside_rig.py W/L20/s3k-seed$s --diagnose --work T \\
        --out enc-seed$s.json; python benchmarks/outside_rig.py W2/L20/s3k-seed$s --diagnose --work T \\
        --out scr-seed$s.json; done
    python benchmarks/outside_rig_seeds.py encoder=enc-seed0.json,enc-seed1.json,enc-seed2.json \\
        scratch=scr-seed0.json,scr-seed1.json,scr-seed2.json --out outside-rig-20.json
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, write_and_emit  # noqa: E402
from s3k.experiments.accuracy import seed_stats  # noqa: E402

IN_RANGE = "train"


def read_model(given: str) -> tuple[str, list[dict[str, Any]]]:
    """``NAME=FILE,FILE,...`` read: the name and each seed's result (with ``file``); raises ValueError naming
    what is wrong."""
    name, sep, files = given.partition("=")
    if not sep or not name or not files:
        raise ValueError(f"{given!r}: expected NAME=FILE[,FILE...] (one outside_rig.py result per seed)")
    results = []
    for path in files.split(","):
        try:
            doc = json.loads(Path(path).read_text())
            rigs = doc["rigs"]
            if IN_RANGE not in rigs:
                raise KeyError(f"no {IN_RANGE!r} rig, the in-range reference")
            for row in rigs.values():
                float(row["median_mm"]), float(row["diagnosis"]["fine_2d_median_px"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"{path}: not an outside_rig.py --diagnose result ({type(e).__name__}: {e})") \
                from None
        results.append(doc | {"file": path})
    return name, results


def test_sets(doc: dict[str, Any]) -> tuple:
    return doc.get("scale"), tuple(doc["rigs"])


def _px(doc: dict[str, Any], rig: str) -> float:
    return float(doc["rigs"][rig]["diagnosis"]["fine_2d_median_px"])


def model_rows(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per rig, the figures of each seed and their means (module docstring)."""
    out: dict[str, Any] = {}
    for rig in results[0]["rigs"]:
        mm = [r["rigs"][rig]["median_mm"] for r in results]
        px = [_px(r, rig) for r in results]
        row = {"median_mm": seed_stats(mm), "fine_2d_median_px": seed_stats(px),
               "rms_mm": seed_stats([r["rigs"][rig]["rms_mm"] for r in results])}
        if rig != IN_RANGE:
            row["median_ratio"] = seed_stats([x / r["rigs"][IN_RANGE]["median_mm"]
                                              for x, r in zip(mm, results)])
            row["fine_2d_ratio"] = seed_stats([x / _px(r, IN_RANGE) for x, r in zip(px, results)])
        out[rig] = row
    return out


def compare(first: list[dict[str, Any]], second: list[dict[str, Any]]) -> dict[str, Any]:
    """Per rig, ``first - second`` seed by seed in 3D and 2D, and the seeds in which ``first`` is lower."""
    out = {}
    for rig in first[0]["rigs"]:
        d3 = [a["rigs"][rig]["median_mm"] - b["rigs"][rig]["median_mm"] for a, b in zip(first, second)]
        d2 = [_px(a, rig) - _px(b, rig) for a, b in zip(first, second)]
        out[rig] = {"median_mm_diff": seed_stats(d3), "fine_2d_px_diff": seed_stats(d2),
                    "seeds_first_lower_3d": sum(x < 0 for x in d3),
                    "seeds_first_lower_2d": sum(x < 0 for x in d2)}
    return out


def summarise(models: list[tuple[str, list[dict[str, Any]]]]) -> dict[str, Any]:
    """The summary (module docstring); raises ValueError where the files do not pair up."""
    if len(models) != 2:
        raise ValueError(f"give two models (NAME=FILE,...), not {len(models)}")
    (one, first), (two, second) = models
    if one == two:
        raise ValueError(f"both models are named {one!r}")
    if len(first) != len(second):
        raise ValueError(f"{one} has {len(first)} seeds and {two} {len(second)}: give each seed's file of "
                         "both")
    for a, b in zip(first, second):
        if test_sets(a) != test_sets(b):
            raise ValueError(f"{b['file']} read other test sets than {a['file']} ({test_sets(b)} against "
                             f"{test_sets(a)}): give outside_rig.py the same --work, --seed and --rigs")
    return {"test_sets": first[0].get("scale"), "seeds": len(first),
            "models": {name: {"files": [r["file"] for r in results], "runs": [r.get("run") for r in results],
                              "rigs": model_rows(results)} for name, results in models},
            "first_minus_second": {"first": one, "second": two, "rigs": compare(first, second)}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs=2, metavar="NAME=FILE,...",
                   help="each model's outside_rig.py --diagnose results, one per seed, in seed order")
    p.add_argument("--out", default=None, help="JSON file to write")
    p.add_argument("--notes", default=None, help="a note kept in the result (where the runs were trained)")
    a = p.parse_args(argv)
    try:
        summary = summarise([read_model(m) for m in a.models])
    except ValueError as e:
        p.error(str(e))
    for name, model in summary["models"].items():
        for rig, row in model["rigs"].items():
            ratios = (f" (x{row['median_ratio']['mean']:.2f}; 2D x{row['fine_2d_ratio']['mean']:.2f})"
                      if "median_ratio" in row else "")
            print(f"{name:10s} {rig:5s} median {row['median_mm']['mean']:.2f} mm, 2D "
                  f"{row['fine_2d_median_px']['mean']:.2f} px{ratios}", file=sys.stderr)
    diff = summary["first_minus_second"]
    for rig, row in diff["rigs"].items():
        print(f"{diff['first']} - {diff['second']} {rig:5s}: "
              + ", ".join(f"{x:+.2f}" for x in row["median_mm_diff"]["per_seed"])
              + f" mm; lower in {row['seeds_first_lower_3d']} of {summary['seeds']} seeds", file=sys.stderr)
    given = sys.argv[1:] if argv is None else argv
    result = {"command": "python benchmarks/outside_rig_seeds.py " + shlex.join(given),
              "git_revision": git_revision(), **summary}
    if a.notes:
        result["notes"] = a.notes
    write_and_emit(result, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
