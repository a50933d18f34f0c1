"""What the rigid read-out does for a two-pass detector: the same trained passes read with and without it.

A detector trained with ``--layout-tol`` holds its 3D keypoints to the labelled layout at read-out
(docs/method.md, "A rigid object's layout"): a keypoint that breaks it is looked for again where the layout
puts it, and the layout is fitted onto the keypoints. In a two-pass run this acts twice: on the coarse
pass's estimates, which place the crops, and on the refining pass's keypoints. Each RUN is read on DATA's
``--split`` four ways, the rigid read-out off or on in each pass, then on in both with a part of it off (the
check's ties settled by the heatmaps, the coarse heatmaps in the refining search; both off is the read-out
before they were added), and the test metrics of each way printed (median and RMS 3D error, share within 5
and 10 mm; the coarse estimates' median and RMS too).

A run trained before its detectors kept the layout (or without ``--layout-tol``) is read with the layout
triangulated from DATA's labelled frames and ``--layout-tol``.

Example::

    python benchmarks/rigid_readout.py runs/accuracy-box/s3k-seed0 runs/accuracy-box/box384-seed0 \\
        --out docs/results/accuracy/rigid-readout.json
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import add_run_data_arguments, run_data_pairs, split_store, write_runs  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402

#: way -> (rigid read-out in the coarse pass, in the refining pass, ties settled, coarse heatmaps in search)
WAYS = {"neither": (False, False, True, True), "coarse only": (True, False, True, True),
        "refining only": (False, True, True, True), "both": (True, True, True, True),
        "both, ties by order": (True, True, False, True),
        "both, no coarse heatmaps": (True, True, True, False),
        "both, neither of these": (True, True, False, False)}


def _detector(run: Path, rigid: bool, layout, tol: float, ties: bool = True, prior: bool = True):
    """A pass's detector with its rigid read-out on (its own layout, else ``layout`` and ``tol``) or off;
    ``ties`` and ``prior``: :class:`s3k.readout.ReadoutConfig`'s ``layout_ties`` and ``layout_prior``."""
    from dataclasses import replace

    from s3k.detector import OnePassDetector, load_network

    model, meta = load_network(run, "cpu")
    if not rigid:
        meta = replace(meta, layout=None, layout_tol=0.0)
    elif meta.layout_distances is None:
        meta = replace(meta, layout=layout.tolist(), layout_tol=tol)
    detector = OnePassDetector(model.fused(), meta)
    detector.readout = replace(detector.readout, layout_ties=ties, layout_prior=prior)
    return detector


def read(run: Path, data: Path, split: str, tol: float) -> dict:
    """The ways (``WAYS``) of reading ``run`` on ``data``'s ``split``."""
    from s3k.detector import TwoPassDetector, load_network, read_two_pass
    from s3k.inference.evaluate import evaluate_store
    from s3k.train import labelled_distances

    rule, coarse, fine = read_two_pass(run)
    ds, store = split_store(data, split)
    layout = labelled_distances(ds, ds.frames("labelled")).numpy()
    out: dict = {"layout_from": {}}
    for name, (rigid_coarse, rigid_fine, ties, prior) in WAYS.items():
        first = _detector(coarse, rigid_coarse, layout, tol, ties, prior)
        coarse_metrics, _ = evaluate_store(first, store, units=ds.units)
        detector = TwoPassDetector(first, _detector(fine, rigid_fine, layout, tol, ties, prior), rule)
        metrics, _ = evaluate_store(detector, store, units=ds.units)
        out[name] = {"coarse_median_mm": coarse_metrics["median_mm"],
                     "coarse_rms_mm": coarse_metrics["rms_mm"],
                     **{k: metrics[k] for k in ("median_mm", "rms_mm", "pck_5mm", "pck_10mm")}}
        print(f"{run} {name}: coarse {coarse_metrics['median_mm']:.2f} / {coarse_metrics['rms_mm']:.1f} mm; "
              f"median {metrics['median_mm']:.2f} mm, RMS {metrics['rms_mm']:.2f} mm, within 5 / 10 mm "
              f"{100 * metrics['pck_5mm']:.1f}% / {100 * metrics['pck_10mm']:.1f}%", file=sys.stderr)
    for name, path in (("coarse", coarse), ("fine", fine)):
        own = load_network(path, "cpu")[1]
        out["layout_from"][name] = ("the detector" if own.layout_distances is not None
                                    else f"{data}'s labelled frames")
        out.setdefault("layout_tol", {})[name] = own.layout_tol if own.layout_distances is not None else tol
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_run_data_arguments(p)
    p.add_argument("--layout-tol", type=float, default=0.1,
                   help="the tolerance for a detector that did not keep its layout (default 0.1)")
    args = p.parse_args(argv)
    pairs = run_data_pairs(p, args)
    import torch

    torch.set_num_threads(1)
    runs = {run: {"data": data, **read(Path(run), Path(data), args.split, args.layout_tol)}
            for run, data in pairs}
    write_runs("benchmarks/rigid_readout.py", argv, args, runs)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
