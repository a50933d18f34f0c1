"""A two-pass run's crops cut again at another size: the same coarse estimates and the same extent in world
units, ``--size`` pixels a side, so that a refining pass can be retrained on them at another resolution and
compared with the run's own (every split, as ``s3k train --two-pass`` writes them).

Example (the refining pass at 192 px, 1.5 mm per crop pixel on the box, against the run's 128 px)::

    python benchmarks/recrop.py runs/accuracy-box-representative/s3k-seed0 \\
        runs/accuracy-box-representative/box384-L100-representative-seed0 --size 192 --out runs/crops192-s0
    s3k train runs/crops192-s0 --out runs/fine192-s0 --steps 8000 --seed 0 ...
    python benchmarks/error_by_pose.py runs/fine192-s0 runs/crops192-s0
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a two-pass run folder (s3k train --two-pass)")
    p.add_argument("data", help="the dataset it was trained on")
    p.add_argument("--size", type=int, required=True, help="crop side in pixels")
    p.add_argument("--out", required=True, help="crop dataset folder to write (must not exist)")
    args = p.parse_args(argv)
    if args.size < 8:
        p.error(f"--size must be at least 8 pixels, got {args.size}")
    out = Path(args.out)
    if out.exists():
        p.error(f"--out {out} exists; give a new folder")

    from s3k.data import Dataset
    from s3k.detector import CropRule, read_two_pass
    from s3k.train.two_pass import ESTIMATES_FILE, coarse_estimates, write_crops

    run, data = Path(args.run), Path(args.data)
    rule, coarse, _fine = read_two_pass(run)
    ds = Dataset.open(data, cache="none")
    # the run's own coarse estimates of every frame (written by training), computed once if absent
    estimates = coarse_estimates(coarse, data, run / ESTIMATES_FILE)
    new_rule = CropRule(rule.extent, args.size, rule.margin)
    write_crops(data, out, estimates, new_rule)
    emit({"command": "python benchmarks/recrop.py " + " ".join(sys.argv[1:] if argv is None else argv),
          "git_revision": git_revision(), "extent": rule.extent, "size": args.size,
          "crop_pixel": rule.extent / args.size, "units": ds.units, "frames": len(estimates)})
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
