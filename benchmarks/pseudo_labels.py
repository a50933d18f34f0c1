"""What the self-supervised term teaches, by the object's pose: a trained detector's pseudo-labels on the
unlabelled frames, made as training makes them (the run's ``--outlier-px``, ``--pseudo-window`` and
``--layout-tol`` against its labelled frames' layout), against the true 3D points.

For each pose class of :mod:`benchmarks.error_by_pose` (the plane of the first three keypoints facing up,
down or to a side) it prints and writes the share of keypoints whose pseudo-label is kept (``kept``) and the
3D error of the kept ones (median, RMS, share within 10 mm, each keypoint's mean error in the frame of the
true keypoints: ``bias_mm``) and of the ones the checks drop. A pose whose pseudo-labels are mostly dropped
gets little from the unlabelled frames; one whose kept pseudo-labels lean teaches the lean.

The network reads the frames unaugmented and in eval mode (the trained detector, not a training step's).
RUN is one pass (a plain run, or a two-pass run's ``fine`` folder read with its ``crops``, which ``s3k train
--keep-crops`` writes); DATA has ground
truth (points3d.csv).

Example::

    python benchmarks/pseudo_labels.py runs/accuracy-box/s3k-seed0/fine runs/accuracy-box/s3k-seed0/crops \\
        --out pseudo.json
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, write_and_emit  # noqa: E402
from s3k.cli import showing_library_messages  # noqa: E402
from s3k.experiments.poses import POSES, bias, error_stats, pose_classes  # noqa: E402


def table(pseudo: np.ndarray, kept: np.ndarray, truth: np.ndarray, mm: float) -> dict:
    """By pose: the share of keypoints kept and the errors of the kept and dropped pseudo-labels.

    Args:
        pseudo: ``(B, K, 3)`` pseudo-label points (world units; NaN where no triangulation).
        kept: ``(B, K)`` bool, the pseudo-label gives a term.
        truth: ``(B, K, 3)`` true points.
        mm: millimetres per world unit.
    """
    err = mm * np.linalg.norm(pseudo - truth, axis=-1)
    classes = pose_classes(truth)
    out: dict = {}
    for name in ("all", *POSES):
        sel = np.ones(len(truth), bool) if name == "all" else classes == name
        k = kept[sel]
        kept_pts = np.where(k[..., None], pseudo[sel], np.nan)
        out[name] = {"frames": int(sel.sum()), "kept": float(k.mean()) if k.size else float("nan"),
                     "kept_error": {**error_stats(err[sel][k]), **bias(kept_pts, truth[sel], mm)},
                     "dropped_error": error_stats(err[sel][~k])}
    return out


def pseudo_labels(run: Path, data: Path, split: str, batch_size: int = 16):
    """``(pseudo (B, K, 3), kept (B, K), truth (B, K, 3), mm per world unit)`` of ``data``'s ``split``."""
    import torch

    from s3k.base.metrics import mm_per_unit
    from s3k.config import TrainConfig
    from s3k.data.frames import FrameStore, images_to_float, open_dataset
    from s3k.detector import load_network
    from s3k.readout import ReadoutConfig
    from s3k.train.losses import pseudo_labels as make_pseudo_labels
    from s3k.train.validation import labelled_distances

    config = run / "config.json"
    cfg = TrainConfig.from_flat(where=str(config), **json.loads(config.read_text())["config"])
    model, meta = load_network(run, "cpu")
    ds = open_dataset(data, meta.image_size)
    rigid = cfg.self_supervision.layout_tol > 0
    layout = labelled_distances(ds, np.asarray(ds.frames("labelled"))) if rigid else None
    store = FrameStore(ds, np.asarray(ds.frames(split)), preload_mb=0)
    pseudo, kept, truth = [], [], []
    with torch.no_grad():
        for batch in store.batches(batch_size):
            got = ds.points3d(batch.frame_ids)
            if got is None:
                raise SystemExit(f"{data}: no ground-truth 3D points (points3d.csv)")
            images = images_to_float(batch.images, "cpu")
            B, C = images.shape[:2]
            logits = model(images.reshape(B * C, *images.shape[2:])).float()
            logits = logits.reshape(B, C, *logits.shape[1:])
            rule = ReadoutConfig.of_training(cfg.self_supervision, layout)
            X, valid, *_views = make_pseudo_labels(logits, batch.cams, meta.stride, meta.sigma, rule=rule)
            pseudo.append(X.double().numpy())
            kept.append(valid.numpy())
            truth.append(np.where(got[1][..., None], got[0], np.nan))
    return np.concatenate(pseudo), np.concatenate(kept), np.concatenate(truth), mm_per_unit(ds.units)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a run folder of one pass (a two-pass run's fine folder)")
    p.add_argument("data", help="the dataset it reads (a two-pass run's crops folder)")
    p.add_argument("--split", default="unlabelled", help="split to read (default unlabelled)")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    pseudo, kept, truth, mm = pseudo_labels(Path(args.run), Path(args.data), args.split)
    result = {"command": shlex.join(["python", "benchmarks/pseudo_labels.py",
                                   *(sys.argv[1:] if argv is None else argv)]),
              "git_revision": git_revision(), "run": args.run, "data": args.data, "split": args.split,
              "by_pose": table(pseudo, kept, truth, mm)}
    for name, row in result["by_pose"].items():
        k = row["kept_error"]
        print(f"{name}: {row['frames']} frames, {100 * row['kept']:.0f}% of keypoints kept; kept median "
              f"{k.get('median_mm', np.nan):.1f} mm, RMS {k.get('rms_mm', np.nan):.1f} mm; dropped median "
              f"{row['dropped_error'].get('median_mm', np.nan):.1f} mm", file=sys.stderr)
    write_and_emit(result, args.out)
    return 0


if __name__ == "__main__":
    with showing_library_messages():  # the library's notes and warnings, as under s3k
        raise SystemExit(main())
