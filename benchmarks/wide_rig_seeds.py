"""A wider training rig over seeds: the per-seed results of ``benchmarks/wide_rig.py --labels-only
--headline-data ... --compare ... --compare-labels-only ...`` side by side, on the headline's own test
frames (the scene's rig), with the mean and standard deviation over seeds of each model's median, RMS and
share within 10 mm, and the checks a new default rig must pass:

- S3K trained on the wider rig is below labels only trained on it, median and RMS, in every seed;
- against the headline's S3K of the same seed (the scene's rig): the median over seeds, seed by seed.

With ``--outside NAME=FILE ...`` (``benchmarks/outside_rig.py`` results, one per seed and model, e.g.
``scene_rig=s3k-seed1.json wider_rig=s3k-el10-70-seed1-scene-rigs.json``) it also gathers each named model's
median on every test rig outside the scene's as a ratio to its in-range median, seed by seed, with the number
of seeds at most the target (1.3x).

Example (after ``benchmarks/wide_rig.py`` for seeds 0-2)::

    python benchmarks/wide_rig_seeds.py docs/results/accuracy/outside-rig/wide-rig-el10-70-seed*.json \\
        --out docs/results/accuracy/outside-rig/wide-rig-el10-70-seeds.json \\
        --outside scene_rig=docs/results/accuracy/outside-rig/s3k-seed0.json ...
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, write_and_emit  # noqa: E402
from s3k.experiments.accuracy import seed_stats  # noqa: E402

HEADLINE = "headline test frames (the scene's rig)"
#: the four models read on the headline's test frames, by their names in wide_rig.py's results
MODELS = {"this run": "s3k_wider_rig", "labels only": "labels_only_wider_rig",
          "compared run": "s3k_scene_rig", "compared labels only": "labels_only_scene_rig"}
FIGURES = ("median_mm", "rms_mm", "pck_10mm")


def summarise(results: list[dict]) -> dict:
    """The summary of per-seed ``wide_rig.py`` results (module docstring); raises ValueError naming what a
    result lacks."""
    rows = []
    for r in results:
        row = r["test_sets"].get(HEADLINE)
        if row is None:
            raise ValueError(f"seed {r['seed']}: no headline test frames (wide_rig.py --headline-data)")
        missing = [who for who in MODELS if who not in row]
        if missing:
            raise ValueError(f"seed {r['seed']}: {', '.join(missing)} not read (wide_rig.py --labels-only, "
                             "--compare and --compare-labels-only)")
        rows.append(row)
    rigs = {json.dumps(r["training_rig"], sort_keys=True) for r in results}
    if len(rigs) > 1:
        raise ValueError("the results were trained on different rigs: " + "; ".join(sorted(rigs)))
    models = {name: {f: seed_stats([row[who][f] for row in rows]) for f in FIGURES}
              for who, name in MODELS.items()}
    ahead = [row["this run"]["median_mm"] < row["labels only"]["median_mm"]
             and row["this run"]["rms_mm"] < row["labels only"]["rms_mm"] for row in rows]
    below_scene = [row["this run"]["median_mm"] < row["compared run"]["median_mm"] for row in rows]
    return {"seeds": [r["seed"] for r in results], "training_rig": results[0]["training_rig"],
            "scene_rig": results[0]["scene_rig"], "test_frames": rows[0]["this run"]["frames"],
            "models": models,
            "train_cpu_minutes": {"s3k_wider_rig": seed_stats([r["train_cpu_minutes"] for r in results]),
                                  "labels_only_wider_rig": seed_stats([r["labels_only_train_cpu_minutes"]
                                                                  for r in results])},
            "checks": {"s3k_ahead_of_labels_only_every_seed": all(ahead),
                       "s3k_ahead_of_labels_only_per_seed": ahead,
                       "wider_rig_median_below_scene_rig_per_seed": below_scene,
                       "median_minus_scene_rig_mm": seed_stats([row["this run"]["median_mm"]
                                                           - row["compared run"]["median_mm"]
                                                           for row in rows])},
            "runs": {str(r["seed"]): {"s3k": r["run"], "labels_only": r.get("labels_only_run"),
                                      "revision": r["git_revision"]} for r in results}}


def outside(pairs: list[str]) -> dict:
    """``{model: {rig: {"ratio_per_seed": [...], "seeds_within_target": n, ...}}}`` of ``NAME=FILE`` pairs of
    outside_rig.py results (module docstring); raises ValueError on a pair without ``=``."""
    by_model: dict[str, list[dict]] = {}
    for pair in pairs:
        name, sep, path = pair.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--outside {pair!r}: expected NAME=FILE")
        by_model.setdefault(name, []).append(json.loads(Path(path).read_text()) | {"file": path})
    out: dict = {}
    for name, results in by_model.items():
        rigs = [r for r in results[0]["rigs"] if r != "train"]
        out[name] = {"files": [r["file"] for r in results], "runs": [r["run"] for r in results],
                     "in_range_median_mm": [r["rigs"]["train"]["median_mm"] for r in results]}
        for rig in rigs:
            ratios = [r["rigs"][rig]["median_ratio_to_in_range"] for r in results]
            target = results[0]["target_median_ratio_at_most"]
            out[name][rig] = {"ratio_per_seed": ratios, "ratio_mean": statistics.fmean(ratios),
                              "median_mm_per_seed": [r["rigs"][rig]["median_mm"] for r in results],
                              "seeds_within_target": sum(x <= target for x in ratios), "target": target}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+", help="per-seed JSON files of benchmarks/wide_rig.py")
    p.add_argument("--outside", nargs="+", default=[], metavar="NAME=FILE",
                   help="benchmarks/outside_rig.py results of each seed's models, named (module docstring)")
    p.add_argument("--out", default=None, help="JSON file to write")
    a = p.parse_args(argv)
    results = sorted((json.loads(Path(f).read_text()) for f in a.results), key=lambda r: r["seed"])
    try:
        summary = summarise(results)
        if a.outside:
            summary["outside_rigs"] = outside(a.outside)
    except ValueError as e:
        p.error(str(e))
    for name, rigs in summary.get("outside_rigs", {}).items():
        for rig, row in rigs.items():
            if isinstance(row, dict):
                ratios = row["ratio_per_seed"]
                print(f"{name:14s} {rig:5s} x in-range per seed " + ", ".join(f"{x:.2f}" for x in ratios)
                      + f"; within {row['target']}x in {row['seeds_within_target']} of {len(ratios)}",
                      file=sys.stderr)
    for name, figures in summary["models"].items():
        print(f"{name:24s} median {figures['median_mm']['mean']:.2f} +- {figures['median_mm']['sd']:.2f} mm, "
              f"RMS {figures['rms_mm']['mean']:.2f} +- {figures['rms_mm']['sd']:.2f} mm, within 10 mm "
              f"{100 * figures['pck_10mm']['mean']:.1f}%", file=sys.stderr)
    given = sys.argv[1:] if argv is None else argv
    write_and_emit({"command": "python benchmarks/wide_rig_seeds.py " + shlex.join(given),
                    "git_revision": git_revision(), **summary}, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
