"""The benchmark of filtering over time (``benchmarks/filter_tracks.py``): a trained detector tracks the box
along a rendered trajectory (:mod:`s3k.sim.trajectory`), as ``s3k track`` (raw and offline-filtered points)
and as ``s3k stream --filter kalman`` (causal), and each is compared with the true keypoints.

The figures: the 3D error's median and RMS over every frame and keypoint where a point was placed (raw and
filtered on the same frames: those where the raw track has a point), and the causal filter's delay, the
shift of the truth (in frames, -3 to 3) that fits its points best (0: no delay).
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.choices import Device
from s3k.data.formats.calibration_files import read_calibration
from s3k.data.tracks_csv import read_csv
from s3k.detector import Detector
from s3k.inference.kalman import FilterSettings
from s3k.inference.session import RigOptions
from s3k.inference.stream import open_source, stream
from s3k.inference.track import track
from s3k.inference.track_config import TrackConfig
from s3k.inference.track_filter import StreamFilter, layout_shape_of, raw_path
from s3k.sim.trajectory import render_box_trajectory

__all__ = ["delay", "errors", "filter_benchmark", "jitter", "paired_difference"]


def errors(X: np.ndarray, truth: np.ndarray, scale: float = 1.0, mask: np.ndarray | None = None
           ) -> dict[str, float]:
    """Median, 90th percentile and RMS of ``|X - truth|`` (``(T, K, 3)``, times ``scale``) over the points
    finite in both (and in ``mask (T, K)``), and how many."""
    d = np.linalg.norm(X - truth, axis=-1) * scale
    ok = np.isfinite(d) if mask is None else np.isfinite(d) & mask
    d = d[ok]
    return {"median": float(np.median(d)) if len(d) else float("nan"),
            "p90": float(np.percentile(d, 90)) if len(d) else float("nan"),
            "rms": float(np.sqrt(np.mean(d**2))) if len(d) else float("nan"), "points": int(len(d))}


def paired_difference(a: np.ndarray, b: np.ndarray, samples: int = 2000, seed: int = 0) -> dict[str, Any]:
    """``median(b) - median(a)``, ``rms(b) - rms(a)`` and the same of the 90th percentile (``p90``: the large
    errors, which the RMS weighs and the median does not) of two error arrays ``(T, K)`` of the same points
    (NaN where a point is missing in either), each with a 95% percentile bootstrap interval that resamples
    the frames (rows) jointly for both, so that the frames' shared difficulty cancels."""
    ok = np.isfinite(a) & np.isfinite(b)
    rows = np.flatnonzero(ok.any(1))
    rng = np.random.default_rng(seed)

    def stats(pick: np.ndarray) -> tuple[float, float, float]:
        m = ok[pick]
        x, y = a[pick][m], b[pick][m]
        return (float(np.median(y) - np.median(x)),
                float(np.sqrt(np.mean(y**2)) - np.sqrt(np.mean(x**2))),
                float(np.percentile(y, 90) - np.percentile(x, 90)))

    if not len(rows):
        return {"median": None, "rms": None, "p90": None, "frames": 0}
    boot = np.array([stats(rng.choice(rows, len(rows))) for _ in range(samples)])
    value = stats(rows)
    return {"median": value[0], "median_ci95": np.percentile(boot[:, 0], [2.5, 97.5]).tolist(),
            "rms": value[1], "rms_ci95": np.percentile(boot[:, 1], [2.5, 97.5]).tolist(),
            "p90": value[2], "p90_ci95": np.percentile(boot[:, 2], [2.5, 97.5]).tolist(),
            "frames": int(len(rows))}


def jitter(X: np.ndarray, scale: float = 1.0) -> float:
    """Frame-to-frame jitter: the median over frames and keypoints of the norm of the second difference
    ``X[t+1] - 2 X[t] + X[t-1]`` (an acceleration, world units per frame squared, times ``scale``)."""
    a = np.linalg.norm(X[2:] - 2 * X[1:-1] + X[:-2], axis=-1) * scale
    a = a[np.isfinite(a)]
    return float(np.median(a)) if len(a) else float("nan")


def delay(X: np.ndarray, truth: np.ndarray, lags: range = range(-3, 4)) -> tuple[int, dict[int, float]]:
    """``(best, rms)``: the RMS of ``X[t] - truth[t - lag]`` for each lag (on the same frames for all) and
    the lag with the least; a filter that lags by ``d`` frames fits the truth shifted by ``d`` best."""
    m = max(abs(v) for v in lags)
    rms = {}
    for lag in lags:
        a, b = X[m:len(X) - m], truth[m - lag:len(truth) - m - lag]
        d = np.linalg.norm(a - b, axis=-1)
        rms[lag] = float(np.sqrt(np.nanmean(d**2)))
    return min(rms, key=lambda lag: rms[lag]), rms


def _stream_points(run: str | Path, videos: dict[str, Path], calibration: Path, keypoints: list[str],
                   device: Device) -> tuple[np.ndarray, np.ndarray]:
    """``(filtered, raw)`` ``(T, K, 3)``: ``s3k stream --filter kalman`` on the videos, from its lines."""

    detector = Detector.load(run, device)
    rig = read_calibration(calibration).select(list(videos))
    cams = rig.cameras
    sources = {c: open_source(str(p)) for c, p in videos.items()}
    filt = StreamFilter(FilterSettings(), len(keypoints), cams.numpy(), layout_shape_of(detector.meta.layout))
    buf = io.StringIO()
    stream(detector, sources, cams, out=buf, filter=filt, say=lambda text: None)
    lines = [json.loads(line) for line in buf.getvalue().splitlines()]

    def points(key: str) -> np.ndarray:
        return np.array([[line[key][k] if line[key][k] is not None else [np.nan] * 3 for k in keypoints]
                         for line in lines], dtype=np.float64)

    return points("points"), points("raw")


def filter_benchmark(run: str | Path, work: str | Path, frames: int = 300, size: int = 96, seed: int = 0,
                     device: Device = "cpu") -> dict[str, Any]:
    """Render the trajectory into ``work``, track it with ``run`` offline (raw, filtered) and causally, and
    return the figures (module docstring) in millimetres."""

    work = Path(work)
    traj = render_box_trajectory(work / "videos", frames=frames, size=size, seed=seed)
    out = work / "points3d.csv"
    result = track(run, traj.videos, RigOptions(traj.calibration, device=device), out,
          TrackConfig.from_flat(progress=False), overwrite=True)

    def load(path: Path) -> np.ndarray:
        got = read_csv(path, traj.keypoints)
        return np.stack([got[f] for f in range(frames)])

    raw, offline = load(raw_path(out)), load(out)
    causal, stream_raw = _stream_points(run, traj.videos, traj.calibration, traj.keypoints, device)
    truth, mm = traj.points, 1000.0
    placed = np.isfinite(raw).all(-1)
    best, by_lag = delay(causal, truth)
    return {
        "frames": frames, "size": size, "seed": seed, "fps": traj.fps, "keypoints": traj.keypoints,
        "units": "mm",
        "raw": errors(raw, truth, mm), "offline": errors(offline, truth, mm, placed),
        "offline_all_frames": errors(offline, truth, mm),
        "stream_raw": errors(stream_raw, truth, mm), "causal": errors(causal, truth, mm, placed),
        "causal_delay_frames": best, "causal_rms_by_lag": {str(k): v * mm for k, v in by_lag.items()},
        "jitter_mm_per_frame2": {"truth": jitter(truth, mm), "raw": jitter(raw, mm),
                                 "offline": jitter(offline, mm), "causal": jitter(causal, mm)},
        "filter": result.filter_record,
    }
