"""Cameras outside the training rig (``benchmarks/outside_rig.py``): a trained run evaluated on test sets
whose cameras sit outside its training rig's ranges (:mod:`s3k.sim.rigs`: lower and higher elevations,
farther, a wider lens) and on one of the training rig, each median against the in-range one (target: at most
1.3x).

The test sets are rendered once into a working folder (``SCENE{size}-{rig}-test{N}-seed{seed}``, test frames
only), all with one sampling seed, so they show the same object poses and lighting from other cameras; the
seed should be none the run's training data was rendered with. Each set's cameras are measured back from its
calibration (distance and elevation of every camera centre from the scene's nominal aim point, the vertical
field of view from the focal length), so the table shows that they do lie outside the training ranges.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.choices import Device
from s3k.base.metrics import ground_truth_2d, keypoint_order, mm_per_unit
from s3k.data import Dataset
from s3k.data.frames import FrameStore
from s3k.detector import Detector
from s3k.detector.over_frames import detect_store
from s3k.geometry import project
from s3k.geometry.triangulation import triangulate_labels
from s3k.inference.evaluate import evaluate_run
from s3k.sim.rigs import RIGS, describe_rig, rig_sampler
from s3k.sim.scene import CameraSampler

#: The largest ratio of an out-of-range median to the in-range one that meets the target.
TARGET_RATIO = 1.3
#: A range ``(lo, hi)`` of a rig other than the scene's, or None for the scene's own.
Range = tuple[float, float] | None
#: The figures kept per test set.
FIGURES = ("median_mm", "rms_mm", "pck_5mm", "pck_10mm")


def test_set_name(scene: str, size: int, rig: str, test: int, seed: int, elevation: Range = None,
                  distance: Range = None) -> str:
    """A test set's folder name; a base rig other than the scene's adds its ranges (``-el10-85``,
    ``-d0.8-1.2``)."""
    base = "".join(f"-{tag}{r[0]:g}-{r[1]:g}" for tag, r in (("el", elevation), ("d", distance)) if r)
    return f"{scene}{size}-{rig}{base}-test{test}-seed{seed}"


def render_test_sets(scene: str, size: int, test: int, seed: int, work: Path, rigs=RIGS,
                     workers: int | None = None, elevation: Range = None,
                     distance: Range = None) -> dict[str, Path]:
    """Each rig's test set (``test`` frames, no labelled or unlabelled ones), rendered unless it is there;
    the rigs are drawn relative to the scene's rig with ``elevation`` and ``distance`` where given."""
    from s3k.sim.generate import SimulateConfig, simulate

    out = {}
    for rig in rigs:
        path = work / test_set_name(scene, size, rig, test, seed, elevation, distance)
        if not (path / "s3k.json").is_file():
            cfg = SimulateConfig(scene, size=size, labelled=0, unlabelled=0, test=test, seed=seed, rig=rig,
                                 elevation=elevation, distance=distance)
            simulate(cfg, path, workers=workers, progress=False, overwrite=True)
        out[rig] = path
    return out


def measured_cameras(data: Path, target: tuple[float, float, float]) -> dict[str, list[float]]:
    """The ``[min, max]`` over a dataset's test frames and cameras of each camera's distance from ``target``
    (metres), its elevation above the table plane seen from ``target`` (degrees) and its vertical field of
    view (degrees)."""

    ds = Dataset.open(data, cache="none")
    cams = ds.calibration(ds.frames("test"))
    centres = cams.centres().double().numpy().reshape(-1, 3) - np.asarray(target)
    distance = np.linalg.norm(centres, axis=1)
    elevation = np.degrees(np.arcsin(centres[:, 2] / distance))
    height = ds.image_size[1]
    fovy = np.degrees(2 * np.arctan2(height / 2, cams.K[..., 1, 1].double().numpy().reshape(-1)))
    return {k: [float(v.min()), float(v.max())] for k, v in
            (("distance_m", distance), ("elevation_deg", elevation), ("fovy_deg", fovy))}


def outside(measured: dict[str, list[float]], train: dict[str, Any]) -> dict[str, bool]:
    """Per quantity, whether every measured value lies outside the training range (for the field of view:
    a single value, so outside means other than it by more than 0.1 degree)."""
    out = {}
    for k in ("distance_m", "elevation_deg"):
        lo, hi = train[k]
        out[k] = measured[k][1] < lo or measured[k][0] > hi
    out["fovy_deg"] = all(abs(v - train["fovy_deg"]) > 0.1 for v in measured["fovy_deg"])
    return out


def evaluate_rigs(run: Path, sets: dict[str, Path], scene: str, device: Device = "cpu",
                  trained_on: CameraSampler | None = None, drawn_from: CameraSampler | None = None,
                  diagnosis: bool = False) -> dict[str, Any]:
    """The run's figures on every test set, the measured cameras, and each median's ratio to the in-range
    (``train``) one.

    Args:
        trained_on: the rig the run was trained on (default the scene's): what ``outside_training_range``
            measures against.
        drawn_from: the rig the test sets' named rigs were drawn relative to (default ``trained_on``).
        diagnosis: add each set's :func:`diagnose` and :func:`triangulation_floor` (at the in-range set's
            median 2D error of the refining pass) as ``diagnosis``.
    """
    from s3k.sim.scenes import SCENES

    train = trained_on or SCENES[scene].cameras_sampler
    base = drawn_from or train
    ranges = describe_rig(train)
    rows: dict[str, Any] = {}
    for rig, data in sets.items():
        metrics = evaluate_run(run, data, split="test", device=device)
        measured = measured_cameras(data, train.target)
        rows[rig] = {**{k: float(metrics[k]) for k in FIGURES}, "frames": int(metrics["n_frames"]),
                     "sampled": describe_rig(rig_sampler(base, rig)), "measured": measured,
                     "outside_training_range": outside(measured, ranges)}
        if diagnosis:
            rows[rig]["diagnosis"] = diagnose(run, data, device)
    if diagnosis and "train" in rows:
        px = rows["train"]["diagnosis"]["fine_2d_median_px"]
        for rig, data in sets.items():
            rows[rig]["diagnosis"]["triangulation_floor_mm"] = triangulation_floor(data, px)
            rows[rig]["diagnosis"]["triangulation_floor_at_px"] = px
    reference = rows.get("train")
    for rig, row in rows.items():
        if reference is None or rig == "train":
            continue
        ratio = row["median_mm"] / reference["median_mm"] if reference["median_mm"] > 0 else math.inf
        row["median_ratio_to_in_range"] = ratio
        row["rms_ratio_to_in_range"] = (row["rms_mm"] / reference["rms_mm"] if reference["rms_mm"] > 0
                                        else math.inf)
        row["meets_target"] = ratio <= TARGET_RATIO
        if diagnosis:
            floor = reference["diagnosis"]["triangulation_floor_mm"]
            row["diagnosis"]["triangulation_floor_ratio"] = row["diagnosis"]["triangulation_floor_mm"] / floor
    return {"training_rig": ranges, "rigs_drawn_relative_to": describe_rig(base), "rigs": rows,
            "target_median_ratio_at_most": TARGET_RATIO}


def table(result: dict[str, Any]) -> list[str]:
    """The printed table: one line per rig."""
    lines = [f"{'rig':6s} {'median mm':>9s} {'RMS mm':>8s} {'<=10 mm':>8s} {'x in-range':>10s}  cameras"]
    for rig, row in result["rigs"].items():
        ratio = row.get("median_ratio_to_in_range")
        m = row["measured"]
        cams = (f"{m['distance_m'][0]:.2f}-{m['distance_m'][1]:.2f} m, elevation {m['elevation_deg'][0]:.0f}-"
                f"{m['elevation_deg'][1]:.0f} deg, fovy {m['fovy_deg'][0]:.0f} deg")
        lines.append(f"{rig:6s} {row['median_mm']:9.2f} {row['rms_mm']:8.2f} {100 * row['pck_10mm']:7.1f}% "
                     f"{'' if ratio is None else f'{ratio:.2f}x':>10s}  {cams}")
    return lines


def diagnose(run: Path, data: Path, device: Device = "cpu", gross_px: float = 10.0) -> dict[str, float]:
    """Where a two-pass run's error on a test set comes from, pass by pass (medians over the visible
    (view, keypoint) pairs or the frames' keypoints):

    - ``coarse_3d_median_mm`` / ``fine_3d_median_mm``: the coarse pass's and the final points' 3D errors;
    - ``coarse_2d_median_px`` / ``fine_2d_median_px``: the passes' per-view 2D errors in the frames' pixels;
    - ``coarse_2d_gross`` / ``fine_2d_gross``: the share of views off by more than ``gross_px``;
    - ``truth_outside_crop``: the share of views whose true keypoint lies outside the refining pass's crop
      (the coarse pass placed the crop wrong);
    - ``fine_2d_gross_on_another_keypoint``: the share of views whose detection lies within ``gross_px`` of
      another keypoint's true position (a keypoint taken for another, as a symmetric object invites);
    - ``frames_swapped``: the share of frames whose points fit better with two keypoints exchanged.
    """

    detector = Detector.load(run, device)
    ds = Dataset.open(data, cache="none")
    order = keypoint_order(detector.keypoints, ds.keypoints)
    store = FrameStore(ds, np.asarray(ds.frames("test")), preload_mb=0, labels=True, points=True)
    scale = mm_per_unit(ds.units)
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("c2", "f2", "out", "other", "c3", "f3", "swap")}
    for batch, pred in detect_store(detector, store):
        if (pred.coarse is None or pred.pixel_maps is None or batch.points is None
                or batch.points_mask is None):
            raise ValueError(f"{run}: a two-pass run and a test set with 3D points are needed")
        W, H = ds.image_size
        gt, mask = ground_truth_2d(batch, (int(W), int(H)))
        gt, mask = gt[:, :, order], mask[:, :, order]
        coarse_uv, fine_uv = pred.coarse.uv.numpy(), pred.uv.numpy()
        cols["c2"].append(np.linalg.norm(coarse_uv - gt, axis=-1)[mask])
        cols["f2"].append(np.linalg.norm(fine_uv - gt, axis=-1)[mask])
        maps = pred.pixel_maps.numpy()
        in_crop = np.einsum("bcij,bckj->bcki", maps[..., :2, :2], gt) + maps[:, :, None, :2, 2]
        w, h = pred.input_size
        cols["out"].append(~((in_crop >= -0.5) & (in_crop <= np.array([w - 0.5, h - 0.5]))).all(-1)[mask])
        to_all = np.linalg.norm(fine_uv[:, :, :, None] - gt[:, :, None], axis=-1)  # (B, C, K, K)
        K = to_all.shape[-1]
        others = np.where(np.eye(K, dtype=bool) | ~mask[:, :, None, :], np.inf, to_all).min(-1)
        own = np.diagonal(to_all, axis1=2, axis2=3)
        cols["other"].append(((own > gross_px) & (others <= gross_px))[mask])
        X_gt, X_mask = batch.points.double().numpy()[:, order], batch.points_mask.numpy()[:, order]
        for key, X in (("c3", pred.coarse.X.numpy()), ("f3", pred.X.numpy())):
            cols[key].append(scale * np.linalg.norm(X - X_gt, axis=-1)[X_mask & np.isfinite(X).all(-1)])
        X = pred.X.numpy()
        err = np.linalg.norm(X - X_gt, axis=-1)
        swapped = np.zeros(len(X), bool)
        for i in range(K):
            for j in range(i + 1, K):
                other = (np.linalg.norm(X[:, i] - X_gt[:, j], axis=-1)
                         + np.linalg.norm(X[:, j] - X_gt[:, i], axis=-1))
                swapped |= other < err[:, i] + err[:, j]
        cols["swap"].append(swapped)
    a = {k: np.concatenate(v) for k, v in cols.items()}
    return {"coarse_3d_median_mm": float(np.median(a["c3"])), "fine_3d_median_mm": float(np.median(a["f3"])),
            "coarse_2d_median_px": float(np.median(a["c2"])), "fine_2d_median_px": float(np.median(a["f2"])),
            "coarse_2d_gross": float(np.mean(a["c2"] > gross_px)),
            "fine_2d_gross": float(np.mean(a["f2"] > gross_px)),
            "truth_outside_crop": float(np.mean(a["out"])),
            "fine_2d_gross_on_another_keypoint": float(np.mean(a["other"])),
            "frames_swapped": float(np.mean(a["swap"])), "gross_px": gross_px}


def triangulation_floor(data: Path, median_px: float, seed: int = 0) -> float:
    """The median 3D error (mm) of a test set's true keypoints triangulated from every view where they are
    in the image, after isotropic Gaussian noise whose median length is ``median_px`` pixels was added to
    their projections: what the cameras' geometry alone makes of a given 2D error (a rig whose rays meet at
    narrow angles, as cameras all nearly overhead, turns the same 2D error into a larger 3D one)."""
    ds = Dataset.open(data, cache="none")
    ids = np.asarray(ds.frames("test"))
    cams = ds.calibration(ids, dtype=torch.float64)
    truth = ds.points3d(ids)
    if truth is None:
        raise ValueError(f"{data}: a test set with 3D points is needed")
    X_gt, X_mask = truth
    uv, depth = project(cams, torch.as_tensor(X_gt, dtype=torch.float64)[:, None])
    W, H = ds.image_size
    inside = (depth > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= W) & (uv[..., 1] >= 0) & (uv[..., 1] <= H)
    sigma = median_px / math.sqrt(2 * math.log(2))  # the median of a 2D Gaussian's length is 1.1774 sigma
    noise = torch.as_tensor(np.random.default_rng(seed).normal(0.0, sigma, uv.shape))
    X, valid = triangulate_labels(cams, uv + noise, inside)
    err = mm_per_unit(ds.units) * np.linalg.norm(X.numpy() - X_gt, axis=-1)
    return float(np.median(err[valid.numpy() & np.asarray(X_mask, bool)]))
