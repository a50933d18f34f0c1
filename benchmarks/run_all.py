"""Run the speed benchmarks one after the other and record their results with the revision that produced them.

    python benchmarks/run_all.py [--repeats 3] [--out docs/results/benchmarks/benchmarks.json]

Each benchmark runs as its own process (so thread pools and compiled kernels do not leak between them),
``--repeats`` times; its last output line is its JSON result. The file written holds every run's result, the
median of each headline figure over the repeats, the exact commands, the git revision and the machine. The
last line printed is one JSON object with the medians.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.common import git_revision  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402

# name -> (arguments after `python`, the headline figures to take medians of)
BENCHMARKS: dict[str, tuple[list[str], list[str]]] = {
    "triangulation": (["benchmarks/triangulation.py"],
                      ["solves_per_s", "solves_per_s_eager", "solves_per_s_fused",
                       "opencv_loop_solves_per_s"]),
    "inference": (["benchmarks/inference.py", "--size", "128"], ["frames_per_s", "flop_fraction"]),
    "inference_exported": (["benchmarks/inference_exported.py", "--size", "128"],
                           ["frames_per_s", "torchscript_frames_per_s", "pytorch_frames_per_s", "max_diff"]),
    "render": (["benchmarks/render.py", "--size", "128"], ["images_per_s"]),
    "train_step": (["benchmarks/train_step.py", "--size", "128"],
                   ["step_s", "flop_fraction", "loader_fraction", "conv_only_fraction",
                    "gemm_fraction"]),
}


def _numbers(result: dict, prefix: str = "") -> dict[str, float]:
    """Every numeric leaf of a result, keyed by its dotted path (the machine description left out)."""
    out: dict[str, float] = {}
    for k, v in result.items():
        if k == "machine":
            continue
        if isinstance(v, dict):
            out.update(_numbers(v, f"{prefix}{k}."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[f"{prefix}{k}"] = float(v)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=3, help="runs of each benchmark (default 3)")
    p.add_argument("--only", default=None, help="comma-separated benchmark names (default: all)")
    p.add_argument("--out", default=str(ROOT / "docs" / "results" / "benchmarks" / "benchmarks.json"))
    args = p.parse_args(argv)
    names = args.only.split(",") if args.only else list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        p.error(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(BENCHMARKS)}")

    given = argv if argv is not None else sys.argv[1:]
    record: dict = {"command": " ".join(["python benchmarks/run_all.py", *given]),
                    "git_revision": git_revision(), "date": time.strftime("%Y-%m-%d"), "benchmarks": {}}
    medians: dict[str, dict[str, float]] = {}
    for name in names:
        cmd, headline = BENCHMARKS[name]
        runs = []
        for i in range(args.repeats):
            print(f"== {name} ({i + 1}/{args.repeats}): python {' '.join(cmd)}", file=sys.stderr, flush=True)
            proc = subprocess.run([sys.executable, *cmd], cwd=ROOT, capture_output=True, text=True)
            lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
            if proc.returncode != 0 or not lines:
                sys.stderr.write(proc.stdout[-2000:] + proc.stderr[-2000:])
                raise SystemExit(f"benchmark {name} failed (exit {proc.returncode})")
            runs.append(json.loads(lines[-1]))
        numbers = [_numbers(r) for r in runs]
        keys = headline or sorted(set.intersection(*(set(n) for n in numbers)))
        med = {k: statistics.median(n[k] for n in numbers) for k in keys if all(k in n for n in numbers)}
        medians[name] = med
        record["benchmarks"][name] = {"command": "python " + " ".join(cmd), "median": med, "runs": runs}
        print(f"{name}: " + ", ".join(f"{k} {v:.4g}" for k, v in med.items()), file=sys.stderr, flush=True)

    record["machine"] = runs[-1].get("machine") if runs else None
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps({"medians": medians, "git_revision": record["git_revision"],
                      "machine": record["machine"]}))


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        main()
