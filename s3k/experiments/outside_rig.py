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

from s3k.data import Dataset
from s3k.inference.evaluate import evaluate_run
from s3k.sim.rigs import RIGS, describe_rig, rig_sampler

#: The largest ratio of an out-of-range median to the in-range one that meets the target.
TARGET_RATIO = 1.3
#: The figures kept per test set.
FIGURES = ("median_mm", "rms_mm", "pck_5mm", "pck_10mm")


def test_set_name(scene: str, size: int, rig: str, test: int, seed: int) -> str:
    return f"{scene}{size}-{rig}-test{test}-seed{seed}"


def render_test_sets(scene: str, size: int, test: int, seed: int, work: Path, rigs=RIGS,
                     workers: int | None = None) -> dict[str, Path]:
    """Each rig's test set (``test`` frames, no labelled or unlabelled ones), rendered unless it is there."""
    from s3k.sim.generate import SimulateConfig, simulate

    out = {}
    for rig in rigs:
        path = work / test_set_name(scene, size, rig, test, seed)
        if not (path / "s3k.json").is_file():
            cfg = SimulateConfig(scene, size=size, labelled=0, unlabelled=0, test=test, seed=seed, rig=rig)
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


def evaluate_rigs(run: Path, sets: dict[str, Path], scene: str, device: str = "cpu") -> dict[str, Any]:
    """The run's figures on every test set, the measured cameras, and each median's ratio to the in-range
    (``train``) one."""
    from s3k.sim.scenes import SCENES

    train = SCENES[scene].cameras_sampler
    ranges = describe_rig(train)
    rows: dict[str, Any] = {}
    for rig, data in sets.items():
        metrics = evaluate_run(run, data, split="test", device=device)
        measured = measured_cameras(data, train.target)
        rows[rig] = {**{k: float(metrics[k]) for k in FIGURES}, "frames": int(metrics["n_frames"]),
                     "sampled": describe_rig(rig_sampler(train, rig)), "measured": measured,
                     "outside_training_range": outside(measured, ranges)}
    reference = rows.get("train")
    for rig, row in rows.items():
        if reference is None or rig == "train":
            continue
        ratio = row["median_mm"] / reference["median_mm"] if reference["median_mm"] > 0 else math.inf
        row["median_ratio_to_in_range"] = ratio
        row["rms_ratio_to_in_range"] = (row["rms_mm"] / reference["rms_mm"] if reference["rms_mm"] > 0
                                        else math.inf)
        row["meets_target"] = ratio <= TARGET_RATIO
    return {"training_rig": ranges, "rigs": rows, "target_median_ratio_at_most": TARGET_RATIO}


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
