"""Cameras outside the training rig: a trained run's median 3D error on test sets of cameras lower, higher,
farther and with a wider lens than any in training, against its median on the training rig (target <= 1.3x).

Renders ``--test`` test frames of ``--scene`` at ``--size`` px for each rig of s3k.sim.rigs
(``train``, ``low``, ``high``, ``far``, ``wide``; ``s3k simulate --rig``), once, into ``--work``, all from
sampling seed ``--seed`` (the same object poses and lighting; choose a seed the run's data was not rendered
with), evaluates the run on each with ``s3k evaluate``'s metrics, and writes ``--out`` (command, revision,
machine, the run, per rig its figures, the cameras' ranges measured from its calibration, and its median's
ratio to the in-range one). The table is printed, then the result as JSON.

Example::

    python benchmarks/outside_rig.py runs/time-to-accuracy/s3k-seed0 \\
        --out docs/results/accuracy/outside-rig/s3k-seed0.json     # 5 x 50 frames at 384 px
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402
from s3k.experiments.accuracy import without_notes  # noqa: E402
from s3k.experiments.outside_rig import evaluate_rigs, render_test_sets, table  # noqa: E402
from s3k.sim.rigs import RIGS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a run folder of `s3k train` (trained on the scene's training rig)")
    p.add_argument("--scene", default="box", choices=("box", "distractors", "category", "plush"),
                   help="the scene the run was trained on (default box)")
    p.add_argument("--size", type=int, default=384, help="rendered image size (default 384)")
    p.add_argument("--test", type=int, default=50, help="test frames per rig (default 50)")
    p.add_argument("--seed", type=int, default=1000,
                   help="sampling seed of every test set (default 1000: no training seed's)")
    p.add_argument("--rigs", default=",".join(RIGS),
                   help=f"the rigs, train (the in-range reference) first (default {','.join(RIGS)})")
    p.add_argument("--work", default=None, help="folder of the test sets (default runs/outside-rig)")
    p.add_argument("--out", default=None, help="result JSON (default: printed only)")
    p.add_argument("--device", default="cpu", help="where the run is evaluated (default cpu)")
    p.add_argument("--workers", type=int, default=None, help="rendering processes (default: CPUs available)")
    p.add_argument("--notes", default=None,
                   help="text kept in the result, e.g. the revision the run was trained at (left out of the "
                        "recorded command)")
    args = p.parse_args(argv)
    rigs = [r for r in args.rigs.split(",") if r]
    unknown = [r for r in rigs if r not in RIGS]
    if unknown or "train" not in rigs:
        p.error(f"--rigs: {', '.join(RIGS)}, train among them; got {args.rigs!r}")
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    work = Path(args.work or ROOT / "runs" / "outside-rig")
    sets = render_test_sets(args.scene, args.size, args.test, args.seed, work, rigs, workers=args.workers)
    given = without_notes(sys.argv[1:] if argv is None else argv)
    result = {"command": shlex.join(["python", "benchmarks/outside_rig.py", *given]),
              "git_revision": git_revision(), "run": str(Path(args.run).resolve()),
              "scale": f"{args.scene} at {args.size} px, {args.test} test frames per rig, sampling seed "
                       f"{args.seed}",
              **evaluate_rigs(Path(args.run), sets, args.scene, args.device)}
    machine = machine_info()
    result["machine"] = machine
    result["avx512_bf16"] = "avx512_bf16" in machine["cpu_flags"]
    if args.notes:
        result["notes"] = args.notes
    for line in table(result):
        print(line, file=sys.stderr)
    write_and_emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
