"""The plush grasp with the two-pass detectors of the plush accuracy benchmark, over its detector seeds.

For every seed ``s`` of ``--plush-work`` (the working folder of ``benchmarks/accuracy.py --scene plush``:
its runs ``s3k-seedS`` and ``labels_only-seedS``, two-pass detectors trained on 384 px renders with 10
labels), ``s3k robot grasp`` runs ``--trials`` grasps with each detector and with the ground truth, over
``--arrangements`` held-out arrangements in turn (7, 8, 9: the datasets' test arrangements; 10, 11, 12: in
no dataset), the trials' lighting and gripper start drawn from ``(s, trial)``, so the three sources meet the
same trials. Writes ``--results``/grasp.json (command, revision, machine, per seed and model the success
rate, per arrangement, and the aim errors) and replaces ``grasp_success`` in ``--results``/summary.json
(``benchmarks/robot.py``'s, the agents' figures kept), and prints the record as the last line.

Each grasp's result file is kept in ``--plush-work``; one that exists is not run again.

Example::

    python benchmarks/accuracy.py --scene plush --seeds 3 ...    # the detectors: docs/results/accuracy/plush
    python benchmarks/grasp.py --plush-work runs/accuracy-plush   # then about 5 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision, machine_info  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.experiments.accuracy import finished  # noqa: E402
from s3k.robot.results import GRASP_SOURCES as SOURCES  # noqa: E402
from s3k.robot.results import grasps_over_seeds, with_grasp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def grasp_file(work: Path, source: str, seed: int, args) -> Path:
    """The seed's grasp result for ``source``, made with ``s3k robot grasp`` unless it exists."""
    out = work / f"grasp-{source}-seed{seed}-{args.trials}x{args.arrangements}.json"
    if out.is_file():
        return out
    run = work / f"{source}-seed{seed}"
    what = ["--ground-truth", "--size", "96"] if source == "ground_truth" else [str(run)]
    if source != "ground_truth" and not finished(run, 2):
        raise SystemExit(f"{run}: no finished two-pass run (make the detectors "
                         "with benchmarks/accuracy.py --scene plush first, or give --plush-work)")
    cmd = [sys.executable, "-m", "s3k.cli", "robot", "grasp", *what, "--trials", str(args.trials),
           "--arrangements", str(args.arrangements), "--seed", str(seed), "--out", str(out)]
    print("$ " + shlex.join(cmd[2:]), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL, env=dict(os.environ, OMP_NUM_THREADS="1"))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--plush-work", default=str(ROOT / "runs" / "accuracy-plush"),
                   help="working folder of benchmarks/accuracy.py --scene plush "
                        "(default runs/accuracy-plush)")
    p.add_argument("--seeds", type=int, default=3, help="detector seeds 0..N-1 (default 3)")
    p.add_argument("--trials", type=int, default=60, help="grasps per detector and seed (default 60)")
    p.add_argument("--arrangements", type=int, default=6, help="held-out arrangements from 7 on (default 6)")
    p.add_argument("--results", default=str(ROOT / "docs" / "results" / "robot"),
                   help="folder of grasp.json and summary.json (default docs/results/robot)")
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    work, results = Path(args.plush_work), Path(args.results)
    revision = git_revision()
    t0, cpu0 = time.perf_counter(), os.times()
    seeds = list(range(args.seeds))
    files = {(src, s): grasp_file(work, src, s, args) for s in seeds for src in SOURCES}
    docs = {key: json.loads(path.read_text()) for key, path in files.items()}
    record: dict = {
        "command": shlex.join(["python", "benchmarks/grasp.py", *(sys.argv[1:] if argv is None else argv)]),
        "git_revision": revision,
        "machine": machine_info(),
        "scale": (f"plush grasp of the front left paw, {args.trials} trials per detector and seed over "
                  f"{args.arrangements} held-out arrangements (7 to {6 + args.arrangements}), "
                  f"{len(seeds)} detector seeds; detectors: the two-pass runs of {work}"),
        "seeds": seeds,
        "trials_per_seed": args.trials,
        "arrangements": docs[SOURCES[0], 0]["arrangements"],
    }
    record.update(grasps_over_seeds(docs, seeds))
    spent = os.times()
    record["cpu_minutes_this_call"] = (spent.children_user + spent.children_system
                                       - cpu0.children_user - cpu0.children_system) / 60
    record["wall_minutes_this_call"] = (time.perf_counter() - t0) / 60
    results.mkdir(parents=True, exist_ok=True)
    (results / "grasp.json").write_text(json.dumps(record, indent=2) + "\n")
    summary_path = results / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    tests = {}
    for src in ("s3k", "labels_only"):  # the accuracy benchmark's evaluations of these detectors
        paths = [work / f"{src}-seed{s}-test.json" for s in seeds]
        tests[src] = [json.loads(p.read_text()) for p in paths] if all(p.is_file() for p in paths) else None
    summary_path.write_text(json.dumps(with_grasp(summary, record, args.trials, tests), indent=2) + "\n")
    for src in SOURCES:
        print(f"{src:13s} success {record[src]['success_rate']['mean']:.3f} "
              f"(per seed {record[src]['success_rate']['per_seed']}), aim error median "
              f"{record[src]['aim_error_mm_median']:.1f} mm", file=sys.stderr)
    emit(record)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
