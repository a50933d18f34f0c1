"""The results side of ``benchmarks/sessions.py``: each run's test figures per session (``s3k evaluate``'s,
kept beside the run with its per-point 3D errors), the paired differences of two models' errors on the same
points per seed with a t-interval over seeds, and the mean figures over seeds."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import paired, t_interval  # noqa: E402

FIGURES = ("median_mm", "rms_mm", "pck_10mm", "pck_5mm", "rms_px", "n_3d")
SHOWN = ("median_mm", "rms_mm", "pck_10mm")


def log(msg: str) -> None:
    print(f"[sessions {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def test_sessions(data: Path) -> set[str]:
    """The sessions of ``data`` with test frames (none when it does not exist yet)."""
    from s3k.data import Dataset

    if not (data / "s3k.json").is_file():
        return set()
    ds = Dataset.open(data, cache="none")
    return set(ds.session_of(ds.frames("test")).tolist())


def detect(run: Path, data: Path) -> tuple[dict[str, Any], dict[str, Any], dict[str, np.ndarray]]:
    """``s3k evaluate``'s figures of ``run`` on ``data``'s test frames (as :func:`evaluate_run` computes
    them), per session, and the per-point 3D errors: ``{"frames" (F,), "sessions" (F,), "err_mm" (F, K)}``,
    NaN where a point has no truth or no triangulation."""
    from s3k.base.metrics import mm_per_unit, point_errors_mm
    from s3k.inference.evaluate import detect_split, per_session

    detector, ds, metrics, arrays = detect_split(run, data, "test", "cpu")
    _, sessions = per_session(ds, arrays, detector.keypoints)
    if arrays["X_gt"] is None:
        raise SystemExit(f"{data}: its test frames have no 3D points")
    err = point_errors_mm(arrays["X"], arrays["X_valid"], arrays["X_gt"], arrays["X_gt_mask"],
                          mm_per_unit(ds.units))
    frames = np.asarray(arrays["frame_ids"], np.int64)
    points = {"frames": frames, "sessions": np.asarray(ds.session_of(frames)).astype(str),
              "err_mm": err}
    return metrics, sessions, points


def evaluate(run: Path, data: Path, wanted: set[str]) -> dict[str, Any] | None:
    """The run's test figures on ``data`` per session, kept in ``RUN-test.json`` with the per-point 3D errors
    in ``RUN-test.npz`` (evaluated again when a session of ``wanted`` is not there); None for an unfinished
    run."""
    from s3k.run_folder import RunFolder

    cache, points = run.parent / f"{run.name}-test.json", run.parent / f"{run.name}-test.npz"
    if cache.is_file():
        result = json.loads(cache.read_text())
        if points.is_file() and wanted <= set(result["sessions"]):
            return result
    if not RunFolder(run).is_complete():
        return None
    log(f"evaluating {run.name} on {data}")
    metrics, sessions, errors = detect(run, data)
    cpu = RunFolder(run).read_cpu()
    result = {"all_sessions": {k: metrics[k] for k in FIGURES},
              "sessions": {s: {k: m[k] for k in (*FIGURES, "n_frames")} for s, m in sessions.items()},
              "train_cpu_minutes": sum(cpu.values()) / 60 if cpu else None}
    tmp = points.parent / f".{points.name}.writing"
    with open(tmp, "wb") as f:
        np.savez(f, **errors)
    os.replace(tmp, points)
    from s3k.base.fileio import atomic_write_json

    atomic_write_json(result, cache)
    return result


def point_errors(run: Path) -> dict[str, np.ndarray] | None:
    path = run.parent / f"{run.name}-test.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def paired_on(a: dict[str, np.ndarray], b: dict[str, np.ndarray], sessions: list[str]) -> dict[str, Any]:
    """:func:`paired` differences ``a - b`` on the frames of ``sessions`` both were evaluated on."""
    def part(e):
        sel = np.isin(e["sessions"], sessions)
        return e["frames"][sel], e["err_mm"][sel]

    (fa, ea), (fb, eb) = part(a), part(b)
    _, ia, ib = np.intersect1d(fa, fb, return_indices=True)
    return paired(ea[ia], eb[ib])


def differences(first: dict[int, Path], second: dict[int, Path], groups: dict[str, list[str]]) -> dict:
    """Per seed and group of sessions the paired difference of ``first``'s and ``second``'s 3D errors; over
    seeds the mean of those with a 95% t-interval."""
    per_seed: dict[int, dict[str, Any]] = {}
    for seed in first:
        a, b = point_errors(first[seed]), point_errors(second[seed])
        if a is not None and b is not None:
            per_seed[seed] = {g: paired_on(a, b, sessions) for g, sessions in groups.items()}
    over = {}
    for g in groups:
        x = [d[g]["mean_diff_mm"] for d in per_seed.values() if d[g]["mean_diff_mm"] is not None]
        over[g] = {"mean_mm": float(np.mean(x)) if x else None, "ci95_mm": t_interval(x), "seeds": len(x)}
    return {"per_seed": per_seed, "over_seeds": over}


def summarise(results: dict[str, dict[int, dict[str, Any]]]) -> dict[str, Any]:
    """Per model: the mean over seeds of the figures of each session every seed has."""
    out: dict[str, Any] = {}
    for model, per_seed in results.items():
        if not per_seed:
            continue
        sessions = [s for s in next(iter(per_seed.values()))["sessions"]
                    if all(s in r["sessions"] for r in per_seed.values())]
        out[model] = {s: {k: float(np.mean([r["sessions"][s][k] for r in per_seed.values()])) for k in SHOWN}
                      for s in sessions}
    return out
