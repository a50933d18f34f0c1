"""Does re-centring the crops help a two-pass run? Evaluates RUN on DATA's test frames with the crops centred
on the coarse pass's estimate (what s3k does), then again on the refining pass's own estimate, ``--rounds``
times in all, and prints the 3D metrics of each round.

A refining pass that fails because its crop was badly placed should improve from round to round; one that
fails on well-placed crops should not.

Example::

    python benchmarks/recentre.py runs/accuracy-box/s3k-seed2 runs/accuracy-box/box384-seed2 --rounds 3
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import emit, git_revision, machine_info  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a two-pass run folder (s3k train --two-pass)")
    p.add_argument("data", help="its dataset (the test split is used)")
    p.add_argument("--rounds", type=int, default=3, help="crop placements to evaluate (default 3)")
    p.add_argument("--split", default="test")
    args = p.parse_args(argv)

    import torch

    from s3k.data import Dataset
    from s3k.data.tracks_csv import read_csv
    from s3k.detector import read_two_pass
    from s3k.inference.evaluate import evaluate_run
    from s3k.inference.predict import predict_dataset
    from s3k.train.two_pass import write_crops

    def estimates_of(run: Path, data: Path, csv: Path) -> dict:
        predict_dataset(run, data, csv, args.split, device="cpu", overwrite=True)
        return read_csv(csv, keypoints)

    torch.set_num_threads(1)
    run, data = Path(args.run), Path(args.data)
    rule, coarse, fine = read_two_pass(run)
    keypoints = Dataset.open(data, cache="none").keypoints
    rounds = []
    with tempfile.TemporaryDirectory(prefix="s3k-recentre-") as tmp:
        tmp = Path(tmp)
        estimates = estimates_of(coarse, data, tmp / "coarse.csv")
        for i in range(args.rounds):
            crops = write_crops(data, tmp / f"crops{i}", estimates, rule, splits=(args.split,))
            m = evaluate_run(fine, crops, split=args.split, device="cpu", overlays=0)
            rounds.append({"centred_on": "coarse pass" if i == 0 else f"refining pass, round {i}",
                           **{k: m[k] for k in ("median_mm", "rms_mm", "pck_5mm", "pck_10mm")}})
            print(rounds[-1], file=sys.stderr, flush=True)
            estimates = estimates_of(fine, crops, tmp / f"fine{i}.csv")
    emit({"command": "python benchmarks/recentre.py " + " ".join(sys.argv[1:] if argv is None else argv),
          "git_revision": git_revision(), "machine": machine_info(), "rounds": rounds})
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
