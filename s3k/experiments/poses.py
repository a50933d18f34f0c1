"""Where a detector's 3D error comes from, by the object's pose (``benchmarks/error_by_pose.py``), and which
poses the labelled frames of each way of choosing them show (``benchmarks/label_poses.py``).

Poses: the plane of the first three keypoints faces up, down, or to a side (its normal more than 45 degrees
from the world's vertical); the sides are split once more by whether the edge from keypoint 0 to 1 is level
or upright. Collapses (keypoints detected drawn together) and swaps (a keypoint detected nearer another's
true place than its own) are counted apart, and each pose's constant error (``bias``) is taken away once.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.metrics import mm_per_unit
from s3k.data import Dataset
from s3k.data.tracks_csv import read_csv
from s3k.experiments.views import select_frames
from s3k.inference.predict import predict_dataset

COLLAPSE_RATIO = 0.5
POSES = ("normal up", "normal down", "on a side")  # the classes of pose_classes
EDGES = ("edge 0-1 level", "edge 0-1 upright")  # the classes of side_edges


def pose_classes(X: np.ndarray) -> np.ndarray:
    """``(B,)`` "normal up", "normal down" or "on a side" from true points ``X (B, K >= 3, 3)``: the normal of
    the plane through keypoints 0, 1, 2 (``(X1 - X0) x (X2 - X1)``) against the world's z axis."""
    n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 1])
    cos = n[:, 2] / np.linalg.norm(n, axis=-1)
    side = np.where(cos < -np.sqrt(0.5), "normal down", "on a side")
    return np.where(cos > np.sqrt(0.5), "normal up", side)


def side_edges(X: np.ndarray) -> np.ndarray:
    """``(B,)`` for poses on a side, which way the edge from keypoint 0 to 1 runs: "edge 0-1 level" (within
    45 degrees of horizontal: on the box, standing on a long edge) or "edge 0-1 upright" (standing on an
    end), from true points ``X (B, K >= 2, 3)``."""
    x = X[:, 1] - X[:, 0]
    level = np.abs(x[:, 2]) < np.sqrt(0.5) * np.linalg.norm(x, axis=-1)
    return np.where(level, *EDGES)


def mean_pairwise(X: np.ndarray) -> np.ndarray:
    """``(B,)`` mean distance over the pairs of keypoints of each frame (NaN pairs ignored)."""
    d = np.linalg.norm(X[:, :, None] - X[:, None], axis=-1)
    iu = np.triu_indices(X.shape[1], 1)
    pairs = d[:, iu[0], iu[1]]
    n = np.isfinite(pairs).sum(axis=-1)
    return np.where(n > 0, np.nansum(pairs, axis=-1) / np.maximum(n, 1), np.nan)  # NaN: no pair detected


def keypoint_frames(X: np.ndarray) -> np.ndarray:
    """``(B, 3, 3)`` rotations whose rows are the axes of the frame of true keypoints ``X (B, K >= 3, 3)``:
    x along ``X1 - X0``, y the part of ``X1 - X2`` square to x, z = x cross y."""
    x = X[:, 1] - X[:, 0]
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = X[:, 1] - X[:, 2]
    y = y - (y * x).sum(-1, keepdims=True) * x
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def bias(pred: np.ndarray, truth: np.ndarray, mm: float) -> dict:
    """Each keypoint's mean error in the frame of the true keypoints (:func:`keypoint_frames`), mm, and the
    median 3D error once that mean is taken away."""
    e = mm * np.einsum("bij,bkj->bki", keypoint_frames(truth), pred - truth)  # (B, K, 3)
    mean = np.nanmean(e, axis=0) if len(e) else np.full(e.shape[1:], np.nan)
    rest = np.linalg.norm(e - mean, axis=-1)
    rest = rest[np.isfinite(rest)]
    return {"bias_mm": np.round(mean, 3).tolist(),
            "median_mm_without_bias": float(np.median(rest)) if len(rest) else float("nan")}


def error_stats(err: np.ndarray, total: float | None = None) -> dict:
    """Median, RMS and share within 10 mm of the errors ``err`` (mm, NaN ignored), and with ``total`` their
    part of that total squared error."""
    err = err[np.isfinite(err)]
    if not len(err):
        return {"n": 0}
    out = {"n": int(len(err)), "median_mm": float(np.median(err)),
           "rms_mm": float(np.sqrt(np.mean(err ** 2))), "pck_10mm": float(np.mean(err <= 10.0))}
    if total is not None:
        out["share_of_squared_error"] = float(np.sum(err ** 2)) / total
    return out


def _to_every_truth(pred: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d, known)``: ``d (B, K detected, K true)`` each detection's distance to every true keypoint (inf
    where either is missing), ``known (B, K)`` whether a detection's distance to its own is finite."""
    d = np.linalg.norm(pred[:, :, None] - truth[:, None], axis=-1)
    d = np.where(np.isfinite(d), d, np.inf)
    return d, np.isfinite(np.diagonal(d, axis1=1, axis2=2))


def swapped_frames(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``(B,)`` bool: some keypoint is detected nearer another keypoint's true place than its own (a symmetric
    confusion, e.g. a box standing on its end taken upside down)."""
    d, known = _to_every_truth(pred, truth)
    return (known & (d.min(axis=-1) < np.diagonal(d, axis1=1, axis2=2))).any(axis=-1)


def nearest_true(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``(K, K)`` counts: row ``k`` is keypoint ``k``'s detections, column ``j`` how many of them lie nearest
    keypoint ``j``'s true place (the diagonal: their own); which keypoint a swap takes another for. Frames
    where ``k`` is not detected or not known are left out."""
    d, known = _to_every_truth(pred, truth)
    nearest, k = np.argmin(d, axis=-1), pred.shape[1]  # (B, K)
    return np.stack([np.bincount(nearest[known[:, i], i], minlength=k) for i in range(k)])


def by_pose(pred: np.ndarray, truth: np.ndarray, mm: float) -> dict:
    """The error table of predictions ``pred`` against ``truth`` (both ``(B, K, 3)`` in world units, ``mm``
    millimetres each)."""
    err = mm * np.linalg.norm(pred - truth, axis=-1)  # (B, K)
    classes = pose_classes(truth)
    collapsed = mean_pairwise(pred) < COLLAPSE_RATIO * mean_pairwise(truth)
    swapped = swapped_frames(pred, truth) & ~collapsed
    total = float(np.nansum(err ** 2))
    out: dict[str, Any] = {"all": error_stats(err.ravel(), total), "by_pose": {},
                           "collapsed_frames": int(collapsed.sum()), "swapped_frames": int(swapped.sum()),
                           "frames": int(len(err)),
                           "nearest_true": nearest_true(pred[~collapsed], truth[~collapsed]).tolist()}
    for name in POSES:
        sel = classes == name
        out["by_pose"][name] = {"frames": int(sel.sum()), **error_stats(err[sel].ravel(), total),
                                **bias(pred[sel], truth[sel], mm)}
        out["by_pose"][name]["collapsed_frames"] = int((collapsed & sel).sum())
        out["by_pose"][name]["swapped_frames"] = int((swapped & sel).sum())
    side, edges = classes == "on a side", side_edges(truth)
    out["by_pose"]["on a side"]["by_edge"] = {
        edge: {"frames": int((side & (edges == edge)).sum()),
               **error_stats(err[side & (edges == edge)].ravel(), total),
               "swapped_frames": int((swapped & side & (edges == edge)).sum())}
        for edge in EDGES}
    out["collapsed"] = error_stats(err[collapsed].ravel(), total)
    out["not_collapsed"] = error_stats(err[~collapsed].ravel(), total)
    out["swapped"] = error_stats(err[swapped].ravel(), total)
    out["neither"] = error_stats(err[~collapsed & ~swapped].ravel(), total)
    return out


def predictions(run: Path, data: Path, split: str) -> tuple[np.ndarray, np.ndarray, float]:
    """``(predicted, true, mm per world unit)`` points of ``data``'s ``split`` by ``run``."""
    ds = Dataset.open(data, cache="none")
    ids = ds.frames(split)
    truth = ds.points3d(ids)
    if truth is None:
        raise SystemExit(f"{data}: no ground-truth 3D points (points3d.csv)")
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "points.csv"
        predict_dataset(run, data, csv, split=split, device="cpu", overwrite=True)
        points = read_csv(csv, ds.keypoints)
    pred = np.stack([points.get(int(f), np.full((len(ds.keypoints), 3), np.nan)) for f in ids])
    X, mask = truth
    return pred, np.where(mask[..., None], X, np.nan), mm_per_unit(ds.units)


def pose_counts(X: np.ndarray) -> dict[str, int]:
    """How many of the true poses ``X (B, K, 3)`` fall in each class, the poses on a side split by edge."""
    classes, edges = pose_classes(X), side_edges(X)
    out = {name: int((classes == name).sum()) for name in POSES[:2]}
    out.update({f"on a side, {edge}": int(((classes == "on a side") & (edges == edge)).sum())
                for edge in EDGES})
    return out


def labelled_poses(data: Path) -> dict[str, int] | None:
    """:func:`pose_counts` of the labelled frames of the dataset ``data`` (None: no 3D points)."""
    ds = Dataset.open(data, cache="none")
    points = ds.points3d(ds.frames("labelled"))
    return None if points is None else pose_counts(np.where(points[1][..., None], points[0], np.nan))


def true_poses(pool, split: str) -> np.ndarray:
    """``(B, K, 3)`` true 3D keypoints of a split's frames, NaN where not known."""
    points = pool.points3d(pool.frames(split))
    if points is None:
        raise SystemExit(f"{pool.path}: no 3D points; label_poses needs a rendered pool")
    return np.where(points[1][..., None], points[0], np.nan)


def pool_report(path: Path, choices: list[str], labelled: int, seed: int | None) -> dict:
    pool = Dataset.open(path, cache="none")
    if seed is None:
        seed = (pool.source or {}).get("seed")
        if seed is None:
            raise SystemExit(f"{path}: s3k.json records no sampling seed; pass --seed")
    ids = pool.frames("labelled")
    if len(ids) < labelled:
        raise SystemExit(f"{path}: {len(ids)} labelled frames, fewer than --labelled {labelled}")
    poses = true_poses(pool, "labelled")
    test = pose_counts(true_poses(pool, "test"))
    labels = {}
    for choice in choices:
        picked = select_frames(pool, labelled, len(pool.frames("unlabelled")), int(seed), choice=choice)
        labels[choice] = pose_counts(poses[np.searchsorted(ids, picked["labelled"])])
    unlabelled = {c: [p for p, n in test.items() if n and not got[p]] for c, got in labels.items()}
    return {"pool": str(path), "seed": int(seed), "pool_poses": pose_counts(poses), "test_poses": test,
            "labels": labels, "unlabelled_poses": unlabelled}


def label_poses(pools: list[str | Path], choices: list[str], labelled: int, seed: int | None) -> dict:
    """:func:`pool_report` of each rendered pool, and ``missing``: per choice, the pools where some pose the
    test frames show has no label.

    Raises:
        SystemExit: naming a pool that is not a dataset folder.
    """
    for path in pools:
        if not (Path(path) / "s3k.json").is_file():
            raise SystemExit(f"{path}: not a dataset folder (no s3k.json)")
    reports = [pool_report(Path(path), choices, labelled, seed) for path in pools]
    return {"labelled": labelled, "pools": reports,
            "missing": {c: sum(bool(r["unlabelled_poses"][c]) for r in reports) for c in choices}}
