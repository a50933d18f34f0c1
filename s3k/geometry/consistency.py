"""Calibration check from 2D labels (the ``s3k check-calibration`` command; recalibrating a camera from
ChArUco frames: :mod:`s3k.rigcal.recalibration`).

Labels seen by >= 2 cameras are triangulated (unit weights, the solver of docs/method.md#triangulation) and
reprojected:

- **residual**: triangulate from every labelled view, reproject into each labelled view; median and RMS of
  the pixel distance per camera. A bad camera pulls every point it sees, which spreads its error over the rig.
- **leave-one-camera-out (LOO)**: for camera c, triangulate from the *other* labelled views (>= 2), reproject
  into c. A camera whose pose or intrinsics disagree with the rig shows a LOO residual far above the others'.

Inconsistent cameras are named greedily: take the camera with the largest LOO median; it is inconsistent if
its LOO median exceeds both a floor ``min_px`` and ``factor`` times the baseline of the remaining cameras (the
median of their LOO medians computed without it). With three cameras a bad one inflates the others' LOO
too, so the test compares camera pairs instead: the two-view residual (epipolar consistency) of the pair
without camera c against that of the two pairs with it. Drop the named camera and repeat while at least three
cameras remain.

Residuals are in pixels of the dataset's images; proofread tracker output is typically a few pixels off.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import numpy as np
import torch

from s3k.geometry import Cameras, project, triangulate_pixels

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass


def _as_cameras(cams) -> Cameras:
    if isinstance(cams, Cameras):
        return cams.to(torch.float64)
    raise TypeError(f"cams must be s3k.geometry.Cameras, got {type(cams).__name__}")


def _check_inputs(cams: Cameras, uv: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    uv = np.asarray(uv, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    if uv.ndim != 4 or uv.shape[-1] != 2:
        raise ValueError(f"uv must have shape (B, C, K, 2), got {uv.shape}")
    if mask.shape != uv.shape[:-1]:
        raise ValueError(f"mask must have shape {uv.shape[:-1]} (B, C, K), got {mask.shape}")
    C = uv.shape[1]
    if cams.shape[-1] != C:
        raise ValueError(f"cams have {cams.shape[-1]} views, uv has {C} cameras")
    mask = mask & np.isfinite(uv).all(-1)
    return np.where(mask[..., None], uv, 0.0), mask, C


def _triangulate_reproject(cams: Cameras, uv: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, ...]:
    """Triangulate with ``weights (B, C, K)`` (0/1), project into every camera.

    Returns:
        ``proj (B, C, K, 2)`` (NaN where the point is invalid or behind the camera), ``X (B, K, 3)``.
    """
    uv_t = torch.as_tensor(uv, dtype=torch.float64)
    w_t = torch.as_tensor(weights, dtype=torch.float64)
    X, valid = triangulate_pixels(cams, uv_t, w_t)
    # Require >= 2 views explicitly: a point from one ray is not a measurement.
    valid = valid & (w_t.sum(dim=1) >= 2)
    proj, depth = project(cams, X[:, None])
    ok = valid[:, None] & (depth > 1e-9)
    proj = torch.where(ok[..., None], proj, torch.full_like(proj, float("nan")))
    X = torch.where(valid[..., None], X, torch.full_like(X, float("nan")))
    return proj.numpy(), X.numpy()


def reprojection_residuals(cams: Cameras, uv, mask, views=None) -> np.ndarray:
    """Pixel residuals of labels against the reprojection of the point triangulated from ``views``.

    Args:
        cams: cameras ``(C,)`` or ``(B, C)``.
        uv: ``(B, C, K, 2)`` labelled pixels.
        mask: ``(B, C, K)`` True where labelled.
        views: ``(C,)`` bool, the cameras that triangulate (all by default). Residuals are reported for all
            labelled cameras, including those not used.

    Returns:
        ``(B, C, K)`` distances in pixels, NaN where not labelled or the point is not triangulable.
    """
    cams = _as_cameras(cams)
    uv, mask, C = _check_inputs(cams, uv, mask)
    views = np.ones(C, bool) if views is None else np.asarray(views, bool)
    proj, _ = _triangulate_reproject(cams, uv, mask & views[None, :, None])
    res = np.linalg.norm(proj - uv, axis=-1)
    return np.where(mask, res, np.nan)


def leave_one_out_residuals(cams: Cameras, uv, mask, views=None) -> np.ndarray:
    """For each camera c in ``views``: triangulate from the other labelled ``views`` (>= 2), reproject into c.

    Returns:
        ``(B, C, K)`` distances in pixels, NaN where not computed (camera not in ``views``, unlabelled, or
        fewer than two other views).
    """
    cams = _as_cameras(cams)
    uv, mask, C = _check_inputs(cams, uv, mask)
    views = np.ones(C, bool) if views is None else np.asarray(views, bool)
    out = np.full(mask.shape, np.nan)
    for c in np.flatnonzero(views):
        others = views.copy()
        others[c] = False
        proj, _ = _triangulate_reproject(cams, uv, mask & others[None, :, None])
        out[:, c] = np.where(mask[:, c], np.linalg.norm(proj[:, c] - uv[:, c], axis=-1), np.nan)
    return out


def _stats(values: np.ndarray) -> tuple[int, float, float]:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0, float("nan"), float("nan")
    return int(v.size), float(np.median(v)), float(np.sqrt(np.mean(v**2)))


@dataclass
class CameraResidual:
    """Residual statistics of one camera, in pixels."""

    name: str
    n: int
    median_px: float
    rms_px: float
    loo_n: int
    loo_median_px: float
    loo_rms_px: float


@dataclass
class CalibrationCheck:
    """Result of :func:`check_calibration`.

    Attributes:
        cameras: residuals of every camera, all cameras triangulating.
        inconsistent: names of the cameras found inconsistent, in the order found.
        decisions: one line per test made, with the numbers compared.
        consistent: residuals with the inconsistent cameras left out of triangulation (for a left-out camera,
            the residual of its labels against points triangulated from the consistent cameras).
        factor, min_px: the thresholds used.
        notes: other findings (e.g. two cameras with identical parameters, which usually means a copy error).
        undecided: the test stopped before judging every camera (too few points, or a pair that cannot
            triangulate).
        unchecked: cameras with fewer than ``min_points`` leave-one-out residuals (e.g. no labels), which
            the test cannot judge.
    """

    cameras: list[CameraResidual]
    inconsistent: list[str]
    decisions: list[str] = field(default_factory=list)
    consistent: list[CameraResidual] = field(default_factory=list)
    factor: float = 3.0
    min_px: float = 0.0
    notes: list[str] = field(default_factory=list)
    undecided: bool = False
    unchecked: list[str] = field(default_factory=list)
    min_points: int = 10

    def format(self) -> str:
        """A plain-text report."""

        def table(rows: list[CameraResidual]) -> list[str]:
            out = [f"  {'camera':<12} {'points':>7} {'median px':>10} {'rms px':>9}   "
                   f"{'LOO points':>10} {'LOO median':>10} {'LOO rms':>9}"]
            for r in rows:
                out.append(
                    f"  {r.name:<12} {r.n:>7d} {r.median_px:>10.2f} {r.rms_px:>9.2f}   "
                    f"{r.loo_n:>10d} {r.loo_median_px:>10.2f} {r.loo_rms_px:>9.2f}"
                )
            return out

        lines = ["reprojection residual per camera (all cameras triangulate; LOO = leave that camera out):"]
        lines += table(self.cameras)
        lines += [f"note: {n}" for n in self.notes]
        lines.append(f"consistency test (factor {self.factor:g}, floor {self.min_px:.2f} px):")
        lines += [f"  {d}" for d in self.decisions]
        if self.inconsistent:
            lines.append(f"INCONSISTENT: {', '.join(self.inconsistent)}")
            lines.append("residual with the consistent cameras only triangulating:")
            lines += table(self.consistent)
        elif self.undecided:
            lines.append("no camera could be judged inconsistent, but the test was incomplete (see above)")
        elif not self.unchecked:
            lines.append("all cameras consistent")
        if self.unchecked:
            counts = {r.name: r.loo_n for r in self.cameras}
            lines.append(f"could not check camera(s) {', '.join(self.unchecked)}: "
                         + ", ".join(f"{c} has {counts.get(c, 0)}" for c in self.unchecked)
                         + f" leave-one-out residuals, fewer than the {self.min_points} the test needs "
                         "(label more keypoints in them)" + ("" if self.inconsistent or self.undecided else
                                                    "; the others are consistent"))
        return "\n".join(lines)


def _residual_rows(names, res, loo) -> list[CameraResidual]:
    rows = []
    for c, name in enumerate(names):
        rows.append(CameraResidual(name, *_stats(res[:, c]), *_stats(loo[:, c])))
    return rows


def identical_cameras(cams: Cameras, names: list[str]) -> list[str]:
    """``"A and B have identical calibration parameters"`` for every pair of cameras ``(C,)`` or ``(B, C)``
    whose parameters are equal (a copy error; the first finding of :func:`check_calibration`, which needs
    no labels)."""
    cams = _as_cameras(cams)
    C = len(names)
    lead = len(cams.shape)
    fields = [v.reshape(-1, C, *v.shape[lead:]) for v in cams.numpy().values()]
    return [f"{names[a]} and {names[b]} have identical calibration parameters"
            for a in range(C) for b in range(a + 1, C)
            if all(np.array_equal(v[:, a], v[:, b]) for v in fields)]


def check_calibration(
    cams: Cameras,
    uv,
    mask,
    names: list[str],
    factor: float = 3.0,
    min_px: float | None = None,
    min_points: int = 10,
    image_size: tuple[int, int] | None = None,
) -> CalibrationCheck:
    """Per-camera residuals, leave-one-camera-out residuals, and the cameras inconsistent with the rest.

    Args:
        cams: cameras ``(C,)`` or ``(B, C)``.
        uv: ``(B, C, K, 2)`` labels in pixels.
        mask: ``(B, C, K)`` True where labelled.
        names: the ``C`` camera names.
        factor: a camera is inconsistent when its LOO median exceeds ``factor`` times the others' baseline...
        min_px: ...and ``min_px`` pixels, so that label noise on a good rig is not flagged. By default 0.5% of
            the image diagonal (8 px at 1280x1024): errors below that are within what hand or tracker labels
            of animals show between good views.
        image_size: ``(W, H)`` for the default ``min_px``; by default twice the principal point.
        min_points: cameras with fewer LOO residuals than this are not judged.

    Returns:
        A :class:`CalibrationCheck`; ``.format()`` gives the report.
    """
    cams = _as_cameras(cams)
    C = len(names)
    if np.asarray(uv).ndim == 4 and np.asarray(uv).shape[1] != C:
        raise ValueError(f"names has {C} cameras, uv has {np.asarray(uv).shape[1]}")
    res = reprojection_residuals(cams, uv, mask)
    notes = identical_cameras(cams, names)
    loo = leave_one_out_residuals(cams, uv, mask)
    if min_px is None:
        if image_size is None:
            pp = cams.K[..., :2, 2].reshape(-1, 2).mean(dim=0).numpy()
            image_size = (2 * pp[0] + 1, 2 * pp[1] + 1)
        min_px = 0.005 * float(np.hypot(*image_size))
    check = CalibrationCheck(_residual_rows(names, res, loo), [], factor=factor, min_px=min_px, notes=notes,
                             min_points=min_points)
    check.unchecked = [r.name for r in check.cameras if r.loo_n < min_points]

    active = np.ones(C, bool)
    while active.sum() >= 3:
        loo_a = leave_one_out_residuals(cams, uv, mask, active)
        medians = {int(c): _stats(loo_a[:, c]) for c in np.flatnonzero(active)}
        judged = {c: m for c, (n, m, _) in medians.items() if n >= min_points}
        if not judged:
            check.decisions.append("too few points seen by >= 3 cameras to judge")
            check.undecided = True
            break
        if active.sum() >= 4:
            worst = max(judged, key=lambda c: judged[c])
            rest = active.copy()
            rest[worst] = False
            loo_rest = leave_one_out_residuals(cams, uv, mask, rest)
            others = [m for c in np.flatnonzero(rest) if np.isfinite(m := _stats(loo_rest[:, c])[1])]
            base = float(np.median(others)) if others else float("nan")  # nan: judged against min_px alone
            value = judged[worst]
            what = f"LOO median {value:.2f} px vs the others' LOO without it {base:.2f} px"
        else:
            # Three cameras: a bad one inflates both LOO of the others, so compare camera pairs instead. The
            # two-view residual of a pair measures its epipolar consistency; a bad camera is in both bad ones.
            idx = [int(i) for i in np.flatnonzero(active)]
            pair: dict[frozenset[int], float] = {}
            for i, a in enumerate(idx):
                for b in idx[i + 1:]:
                    views = np.zeros(C, bool)
                    views[[a, b]] = True
                    r = reprojection_residuals(cams, uv, mask, views)[:, [a, b]]
                    pair[frozenset((a, b))] = _stats(r)[1]
            without = {c: pair[frozenset(set(idx) - {c})] for c in idx}
            if any(not np.isfinite(v) for v in pair.values()):
                broken = [" and ".join(names[c] for c in sorted(k)) for k, v in pair.items()
                          if not np.isfinite(v)]
                check.decisions.append(
                    f"cannot judge {', '.join(names[c] for c in idx)}: {'; '.join(broken)} triangulate no "
                    "point together (same centre, or no shared labels)"
                )
                check.undecided = True
                break
            worst = min(without, key=lambda c: without[c])
            base = without[worst]
            value = float(np.median([v for k, v in pair.items() if worst in k]))
            rest = active.copy()
            rest[worst] = False
            what = f"two-view residual of its pairs {value:.2f} px vs of the other pair {base:.2f} px"
        bad = value > max(min_px, factor * base)
        check.decisions.append(f"{names[worst]}: {what} -> " + ("INCONSISTENT" if bad else "consistent"))
        if not bad:
            break
        check.inconsistent.append(names[worst])
        active = rest
    if check.inconsistent:
        res_c = reprojection_residuals(cams, uv, mask, active)
        loo_c = leave_one_out_residuals(cams, uv, mask, active)
        # A left-out camera's "LOO" is its residual against the consistent cameras' points.
        for c in np.flatnonzero(~active):
            loo_c[:, c] = res_c[:, c]
        check.consistent = _residual_rows(names, res_c, loo_c)
    return check
