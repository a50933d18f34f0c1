"""The inference benchmark at an earlier revision and at this checkout, side by side:
``benchmarks/inference.py`` run alternately from a ``git archive`` of REVISION and from here (A B A B ...), so
that a shared machine's drift hits both alike. Prints and writes each pipeline's frames/s per run, their
medians, and the median of the pairwise ratios (this checkout over REVISION); a ratio near 1 says the code in
between left inference speed as it was.

    python benchmarks/inference_revisions.py e36f624 --pairs 3 [--out FILE.json] [-- inference.py options]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def run_once(src: Path, options: list[str]) -> dict:
    """One run of ``benchmarks/inference.py`` from the tree ``src``: its last line's JSON."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    out = subprocess.run([sys.executable, str(src / "benchmarks" / "inference.py"), *options], cwd=src,
                         env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("revision", help="the earlier revision (anything git archive takes)")
    p.add_argument("--pairs", type=int, default=3, help="runs of each, alternated (default 3)")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    p.add_argument("options", nargs="*", help="options of benchmarks/inference.py (after --)")
    a = p.parse_args(argv)
    options = a.options or ["--batch", "1", "--threads", "1", "--rounds", "2", "--no-reference"]
    runs: dict[str, list[dict]] = {"then": [], "now": []}
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "archive", a.revision], cwd=ROOT, capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", tmp], input=archive.stdout, check=True)
        for i in range(a.pairs):
            for side, src in (("then", Path(tmp)), ("now", ROOT)):
                runs[side].append(run_once(src, options))
                fps = {k: round(v["frames_per_s"], 1) for k, v in runs[side][-1]["pipelines"].items()}
                print(f"pair {i + 1} {side}: {fps}", flush=True)
    pipelines = sorted(set(runs["then"][0]["pipelines"]) & set(runs["now"][0]["pipelines"]))
    table = {}
    for name in pipelines:
        then = [r["pipelines"][name]["frames_per_s"] for r in runs["then"]]
        now = [r["pipelines"][name]["frames_per_s"] for r in runs["now"]]
        ratios = [n / t for n, t in zip(now, then)]
        table[name] = {"then_frames_per_s": then, "now_frames_per_s": now,
                       "then_median": statistics.median(then), "now_median": statistics.median(now),
                       "ratio_median": statistics.median(ratios), "ratios": ratios}
        print(f"{name}: {a.revision} {table[name]['then_median']:.1f} frames/s, this checkout "
              f"{table[name]['now_median']:.1f}; ratio now/then median {table[name]['ratio_median']:.3f} "
              f"({', '.join(f'{r:.3f}' for r in ratios)})", flush=True)
    result = {"command": shlex.join(["python", "benchmarks/inference_revisions.py",
                                     *(sys.argv[1:] if argv is None else argv)]),
              "revision": git_revision(), "against": a.revision, "inference_options": options,
              "machine": machine_info(), "pipelines": table}
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
