"""One benchmark script under two checkouts of s3k, alternately, so that a shared machine's drift hits both
alike: ``--runs`` calls each, in the order before, after, before, after, ...; each call's last line is its
JSON. Prints one JSON object: the command, both revisions and, per pipeline, every call's frames per second
and their median, the ratio of the medians (after / before) and of each pair of calls made one after the
other, with their median (the ratio a shared machine's drift between pairs leaves alone).

Example (a checkout of the earlier revision in /tmp/before)::

    python benchmarks/side_by_side.py --before /tmp/before --runs 3 -- benchmarks/inference.py --threads 1
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def revision(checkout: Path) -> str:
    return subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()


def call(checkout: Path, script: list[str]) -> dict:
    """One call of the benchmark ``script`` (path relative to the checkout, then its options) there."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    out = subprocess.run([sys.executable, str(checkout / script[0]), *script[1:]], cwd=checkout, env=env,
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the checkout of the earlier revision")
    p.add_argument("--after", default=str(ROOT), help="the checkout of the later one (default: this one)")
    p.add_argument("--runs", type=int, default=3, help="calls of each (default 3)")
    p.add_argument("script", nargs=argparse.REMAINDER, help="-- SCRIPT [OPTIONS]")
    args = p.parse_args(argv)
    script = args.script[1:] if args.script[:1] == ["--"] else args.script
    sides = {"before": Path(args.before).resolve(), "after": Path(args.after).resolve()}
    calls: dict[str, list[dict]] = {side: [] for side in sides}
    for _ in range(args.runs):
        for side, checkout in sides.items():
            calls[side].append(call(checkout, script))
    pipelines = {}
    for name in calls["before"][0]["pipelines"]:
        fps = {side: [c["pipelines"][name]["frames_per_s"] for c in got] for side, got in calls.items()}
        med = {side: statistics.median(v) for side, v in fps.items()}
        # each after call is compared with the before call just ahead of it: the machine's drift between
        # pairs does not enter the ratio
        pairs = [a / b for a, b in zip(fps["after"], fps["before"])]
        pipelines[name] = {"frames_per_s": fps, "median": med,
                           "after_over_before": med["after"] / med["before"],
                           "after_over_before_pairs": pairs,
                           "after_over_before_pairs_median": statistics.median(pairs)}
    print(json.dumps({
        "command": shlex.join(["python", "benchmarks/side_by_side.py",
                               *(sys.argv[1:] if argv is None else argv)]),
        "revisions": {side: revision(path) for side, path in sides.items()},
        "machine": calls["after"][-1].get("machine"), "device": calls["after"][-1].get("device"),
        "pipelines": pipelines}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
