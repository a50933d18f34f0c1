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
    python benchmarks/outside_rig.py runs/wide-rig/s3k-seed0 --elevation 10,85 --diagnose \
        --out docs/results/accuracy/outside-rig/s3k-el10-85-seed0.json  # trained on a wider rig: the rigs
                                                                         # outside that one
    python benchmarks/outside_rig.py runs/wide-rig/s3k-seed0 --elevation 10,85 --rigs-from scene  # and on
                                                                         # the scene's rig's outside sets

``--diagnose`` adds per rig where the error comes from (s3k.experiments.outside_rig.diagnose): the coarse
and the refining pass's 2D and 3D errors, crops that miss, keypoints taken for others, and the cameras'
triangulation floor: the 3D error their geometry alone makes of the in-range set's 2D error.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402
from s3k.cli.simulate import number_pair  # noqa: E402
from s3k.experiments.accuracy import without_notes  # noqa: E402
from s3k.experiments.outside_rig import evaluate_rigs, render_test_sets, table  # noqa: E402
from s3k.sim.rigs import RIGS, describe_rig  # noqa: E402

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
    p.add_argument("--elevation", type=number_pair, default=None, metavar="LO,HI",
                   help="the run's training rig's elevations in degrees, when its data was rendered with "
                        "`s3k simulate --elevation` (default the scene's)")
    p.add_argument("--distance", type=number_pair, default=None, metavar="LO,HI",
                   help="the run's training rig's distances in metres (`s3k simulate --distance`; default "
                        "the scene's)")
    p.add_argument("--rigs-from", choices=("run", "scene"), default="run",
                   help="draw the named rigs relative to the run's training rig (run, the default) or to the "
                        "scene's own (scene: the same test sets as for a run trained on the scene's rig)")
    p.add_argument("--diagnose", action="store_true",
                   help="also per rig where the error comes from: each pass's 2D and 3D errors, crops that "
                        "miss, keypoints taken for others, and the triangulation floor of its cameras")
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
    from s3k.sim.rigs import ranged_sampler
    from s3k.sim.scenes import SCENES

    scene_rig = SCENES[args.scene].cameras_sampler
    try:
        trained_on = ranged_sampler(scene_rig, args.elevation, args.distance)
    except ValueError as e:
        p.error(str(e))
    base = (args.elevation, args.distance) if args.rigs_from == "run" else (None, None)
    sets = render_test_sets(args.scene, args.size, args.test, args.seed, work, rigs, workers=args.workers,
                            elevation=base[0], distance=base[1])
    given = without_notes(sys.argv[1:] if argv is None else argv)
    result = {"command": shlex.join(["python", "benchmarks/outside_rig.py", *given]),
              "git_revision": git_revision(), "run": str(Path(args.run).resolve()),
              "scale": f"{args.scene} at {args.size} px, {args.test} test frames per rig, sampling seed "
                       f"{args.seed}",
              "scene_rig": describe_rig(scene_rig),
              **evaluate_rigs(Path(args.run), sets, args.scene, args.device, trained_on=trained_on,
                              drawn_from=trained_on if args.rigs_from == "run" else scene_rig,
                              diagnosis=args.diagnose)}
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
