"""How far a calibration can be trusted, from the board frames themselves: what detection took and dropped;
each camera's error on board frames held out of its fit (the rig calibrated from scratch on the first half of
the frames, the board poses of the second half fitted to it with the cameras held, and the other way round:
contiguous blocks, not interleaved frames, which share the board's positions and agree optimistically); the
two halves' rigs against each other; the board's square measured between triangulated neighbouring corners
against its known side; the share of each image the board covered; each camera's centre and orientation
spread over bootstrap resamples of the board frames; and warnings that say what to record next.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.geometry import Cameras, triangulate_pixels
from s3k.rigcal.board_sync import frame_offsets
from s3k.rigcal.boards import Detections
from s3k.rigcal.bundle import Adjusted, bundle_adjust
from s3k.rigcal.rig import RigCalibration, calibrate_detections
from s3k.rigcal.solve import Observations

HELD_OUT_MAX_PX = 1.0
"""Held-out median error above which the board frames did not pin the rig down (warned)."""
SQUARE_MAX_ERROR = 0.005
"""Relative error of the triangulated square above which the scale is warned of (0.5%)."""
COVERAGE_MIN = 0.25
"""Share of a camera's image (cells of an 8 x 8 grid holding a corner) below which its edges are
unconstrained (warned)."""
DROPPED_MAX = 0.2
"""Share of a camera's board views left out as wrong reads above which it is warned of."""
OFFSET_GAIN = 0.5
"""A frame offset is warned of when the board fits the camera at most this share of its unshifted error."""
MIN_HALF_VIEWS = 3
"""Board views a camera needs in a half for that half to fit it."""


@dataclass
class Report:
    """The figures (JSON-ready) and the warnings, each naming what to record next."""

    figures: dict
    warnings: list[str] = field(default_factory=list)

    def format(self) -> str:
        f = self.figures
        lines = [
            f"{'camera':<12}{'images':>7}{'board':>7}{'inverted':>9}{'back':>6}{'stray ids':>10}"
            f"{'dropped':>9}{'frame offset':>13}"
        ]
        for name, d in f["detections"].items():
            offset = f["frame_offsets"][name]["offset"]
            shift = "-" if offset is None else f"{offset:+d}" if offset else "0"
            lines.append(
                f"{name:<12}{d['images']:>7}{d['board_frames']:>7}{d['inverted']:>9}{d['back_face']:>6}"
                f"{d['stray_markers']:>10}{d['views_dropped']:>9}{shift:>13}"
            )
        h = f["halves"]
        lines.append(
            f"held out: the rig fitted on frames {h['first']} or {h['second']}, the other half's board "
            "poses fitted to it (median px); spread over "
            f"{f['bootstrap']['resamples']} bootstrap resamples of the board frames"
        )
        lines.append(
            f"{'camera':<12}{'1st->2nd':>9}{'2nd->1st':>9}{'halves mm':>10}{'halves deg':>11}"
            f"{'centre +-mm':>12}{'turn +-deg':>11}{'coverage':>9}"
        )
        for name in f["detections"]:
            a, b = h["first_on_second_px"][name], h["second_on_first_px"][name]
            d, s = h["rigs_apart"][name], f["bootstrap"]["cameras"][name]
            lines.append(
                f"{name:<12}{_num(a, 9)}{_num(b, 9)}{_num(d['centre_mm'], 10, 1)}"
                f"{_num(d['orientation_deg'], 11)}{_num(s['centre_mm'], 12, 1)}"
                f"{_num(s['orientation_deg'], 11)}{f['coverage'][name]:>9.0%}"
            )
        sq = f["square"]
        lines.append(
            f"square {sq['known']:g}: triangulated {_num(sq['all_frames'], 0, 3).strip()} with the whole "
            f"rig ({_pct(sq['all_frames_error'])}), {_num(sq['held_out'], 0, 3).strip()} held out "
            f"({_pct(sq['held_out_error'])}); the halves' rigs differ in scale by "
            f"{_pct(h['scale_difference'])}"
        )
        lines += [f"warning: {w}" for w in self.warnings] or ["no warning"]
        return "\n".join(lines)

    def write(self, path) -> None:
        atomic_write_json({**self.figures, "warnings": self.warnings}, path, indent=1)


def _num(x, width: int, digits: int = 2) -> str:
    return f"{'-':>{width}}" if x is None else f"{x:>{width}.{digits}f}"


def _pct(x) -> str:
    return "-" if x is None else f"{x:+.2%}"


def _cameras(adj: Adjusted) -> Cameras:
    return Cameras.from_numpy(
        np.stack([i.K() for i in adj.intrinsics]),
        np.stack([i.dist() for i in adj.intrinsics]),
        np.stack(adj.R),
        np.stack(adj.t),
        dtype=torch.float64,
    )


def _views(obs: Observations, chosen: list[int]) -> Observations:
    """The board observations of the views ``chosen`` (repeats allowed), renumbered ``0..len(chosen)-1``."""
    parts = [np.flatnonzero(obs.view == v) for v in chosen]
    rows = np.concatenate(parts) if parts else np.zeros(0, int)
    view = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)]) if parts else np.zeros(0, int)
    return Observations(obs.cam[rows], view, obs.corner[rows], obs.uv[rows])


def _detected(cal: RigCalibration) -> tuple[Observations, list[int]]:
    """Every camera's detected board corners (views of 6 corners or more), whether the calibration kept them
    or left them out as wrong reads: the held-out figures judge a rig on all it would meet. Returns the
    observations and the frame key of each view."""
    keys = sorted({k for d in cal.detections for k, (ids, _) in d.frames.items() if len(ids) >= 6})
    pos = {k: v for v, k in enumerate(keys)}
    cam, view, corner, uv = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros((0, 2))]
    for c, d in enumerate(cal.detections):
        for k, (ids, pts) in d.frames.items():
            if k in pos and len(ids) >= 6:
                cam.append(np.full(len(ids), c))
                view.append(np.full(len(ids), pos[k]))
                corner.append(ids)
                uv.append(pts)
    obs = Observations(np.concatenate(cam), np.concatenate(view), np.concatenate(corner), np.concatenate(uv))
    return obs, keys


def _corners3d(cal: RigCalibration) -> np.ndarray:
    b = cal.board
    return b.cv2_board().getChessboardCorners().astype(np.float64) if b.charuco else b.corners3d()


def _refit(cal: RigCalibration, chosen: list[int], evaluations: int = 50) -> Adjusted:
    """The bundle adjustment on the views ``chosen`` (repeats allowed) started from the whole calibration,
    every camera and board pose free (the first camera the world)."""
    a, o = cal.adjusted, cal.options
    return bundle_adjust(
        a.intrinsics,
        a.R,
        a.t,
        [cal.adjusted.views[v] for v in chosen],
        _views(cal.observations, chosen),
        _corners3d(cal),
        fixed=o.get("fixed"),
        free_principal_point=o.get("free_principal_point", False),
        radial=o.get("radial", 2),
        loss_scale_px=o.get("loss_scale_px", 1.0),
        max_evaluations=evaluations,
    )


def _centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -R.T @ t


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def _square(
    cal: RigCalibration, obs: Observations, adj: Adjusted, chosen: list[int], used: list[int]
) -> float | None:
    """Median distance between neighbouring board corners of the views ``chosen``, each corner triangulated
    by the cameras ``adj`` from every camera of ``used`` that saw it (two at least)."""
    C, N = len(cal.names), len(_corners3d(cal))
    nx = cal.board.squares_x - 1
    uv = np.zeros((len(chosen), C, N, 2))
    w = np.zeros((len(chosen), C, N))
    for i, v in enumerate(chosen):
        sel = (obs.view == v) & np.isin(obs.cam, used)
        uv[i, obs.cam[sel], obs.corner[sel]] = obs.uv[sel]
        w[i, obs.cam[sel], obs.corner[sel]] = 1.0
    if not len(chosen):
        return None
    points, valid = triangulate_pixels(_cameras(adj), torch.from_numpy(uv), torch.from_numpy(w))
    X, ok = points.numpy(), valid.numpy() & (w.sum(1) >= 2)
    k = np.arange(N)
    pairs = [(a, a + 1) for a in k if a % nx != nx - 1] + [(a, a + nx) for a in k if a + nx < N]
    parts = [np.linalg.norm(X[:, a] - X[:, b], axis=-1)[ok[:, a] & ok[:, b]] for a, b in pairs]
    d = np.concatenate(parts) if parts else np.zeros(0)
    return float(np.median(d)) if len(d) else None


def _calibrate_half(
    cal: RigCalibration, obs: Observations, keys: list[int], half: list[int]
) -> tuple[Adjusted, list[int]]:
    """The rig calibrated from scratch on the board views ``half`` alone (as :func:`calibrate_detections`
    does on all of them), by the cameras with :data:`MIN_HALF_VIEWS` views in it: ``(cameras, their
    indices)``; the other cameras keep the whole calibration's values and are not compared."""
    C = len(cal.names)
    chosen = {keys[v] for v in half}
    used = [
        c
        for c in range(C)
        if len(set(obs.view[(obs.cam == c) & np.isin(obs.view, half)].tolist())) >= MIN_HALF_VIEWS
    ]
    a = cal.adjusted
    intr, R, t = list(a.intrinsics), list(a.R), list(a.t)
    if not used or used[0] != 0:  # the world is the first camera: without it the halves are not compared
        return a, []
    dets = [
        Detections({k: v for k, v in cal.detections[c].frames.items() if k in chosen}, cal.detections[c].size)
        for c in used
    ]
    o = cal.options
    try:
        part = calibrate_detections(
            [cal.names[c] for c in used],
            dets,
            cal.board,
            free_principal_point=o.get("free_principal_point", False),
            radial=o.get("radial", 2),
            loss_scale_px=o.get("loss_scale_px", 1.0),
        )
    except UserError:  # the half's views do not link its cameras
        return a, []
    for i, c in enumerate(used):
        intr[c], R[c], t[c] = part.adjusted.intrinsics[i], part.adjusted.R[i], part.adjusted.t[i]
    return Adjusted(intr, R, t, [], np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2)), 0.0, 0), used


def _held_out(
    cal: RigCalibration, obs: Observations, fitted: Adjusted, used: list[int], test: list[int]
) -> dict:
    """Per camera of ``used`` the median residual of its corners in the views ``test`` once each view's
    board pose is fitted to the cameras ``fitted``, held (its start: PnP in the camera with most corners);
    None for the others and for a camera without a corner there."""
    corners3d = _corners3d(cal)
    mine = np.isin(obs.cam, used)
    test = [v for v in test if (mine & (obs.view == v)).any()]
    sub = _views(obs, test)
    keep = np.isin(sub.cam, used)
    sub = Observations(sub.cam[keep], sub.view[keep], sub.corner[keep], sub.uv[keep])
    views = []
    for i in range(len(test)):
        sel = sub.view == i
        c = int(np.bincount(sub.cam[sel]).argmax())
        pick = sel & (sub.cam == c)
        _, rvec, tvec = cv2.solvePnP(
            corners3d[sub.corner[pick]], sub.uv[pick], fitted.intrinsics[c].K(), fitted.intrinsics[c].dist()
        )
        Rb = cv2.Rodrigues(rvec)[0]
        views.append((fitted.R[c].T @ Rb, fitted.R[c].T @ (tvec.reshape(3) - fitted.t[c])))
    out: dict = {n: None for n in cal.names}
    if not test:
        return out
    held = bundle_adjust(
        fitted.intrinsics,
        fitted.R,
        fitted.t,
        views,
        sub,
        corners3d,
        fixed=list(range(len(cal.names))),
        loss_scale_px=cal.options.get("loss_scale_px", 1.0),
    )
    err = np.linalg.norm(held.residuals, axis=1)
    for c in used:
        if (sub.cam == c).any():
            out[cal.names[c]] = float(np.median(err[sub.cam == c]))
    return out


def _bootstrap(cal: RigCalibration, resamples: int, seed: int) -> dict:
    """Per camera the RMS distance of its centre (and RMS angle of its orientation) from the calibration's
    over ``resamples`` refits to board views drawn with replacement (world: the first camera, so it has
    none). Each refit starts from the calibration (cheap): the spread says how much the same frames,
    reweighted, move the rig; a board that never pinned the rig down shows in the halves, which start from
    scratch."""
    rng = np.random.default_rng(seed)
    V, a = len(cal.view_keys), cal.adjusted
    dc: list[list[float]] = [[] for _ in cal.names]
    da: list[list[float]] = [[] for _ in cal.names]
    for _ in range(resamples):
        b = _refit(cal, sorted(rng.integers(0, V, V).tolist()))
        for c in range(len(cal.names)):
            dc[c].append(float(np.linalg.norm(_centre(b.R[c], b.t[c]) - _centre(a.R[c], a.t[c]))))
            da[c].append(_angle_deg(b.R[c] @ a.R[c].T))
    rms = lambda x: float(np.sqrt(np.mean(np.square(x)))) if x else None  # noqa: E731
    return {
        "resamples": resamples,
        "seed": seed,
        "cameras": {
            n: {"centre_mm": rms(dc[c]), "orientation_deg": rms(da[c])} for c, n in enumerate(cal.names)
        },
    }


def calibration_report(cal: RigCalibration, *, resamples: int = 8, seed: int = 0) -> Report:
    """The report of a board calibration (see the module's doc); ``resamples`` bootstrap refits (0: none)."""
    a, names = cal.adjusted, cal.names
    obs, keys = _detected(cal)
    unit = cal.rig().units
    detections = {
        n: {
            "images": d.images,
            "board_frames": len(d.frames),
            "inverted": d.inverted,
            "back_face": d.back,
            "stray_markers": d.stray,
            "stray_frames": d.stray_frames,
            "stray_ids": list(d.stray_ids),
            "views_used": r.views,
            "views_dropped": r.dropped_views,
            "median_px": r.median_px,
            "rms_px": r.rms_px,
        }
        for n, d, r in zip(names, cal.detections, cal.report)
    }
    V = len(keys)
    first, second = list(range(V // 2)), list(range(V // 2, V))
    (fit1, used1), (fit2, used2) = (
        _calibrate_half(cal, obs, keys, first),
        _calibrate_half(cal, obs, keys, second),
    )
    c1 = [_centre(R, t) for R, t in zip(fit1.R, fit1.t)]
    c2 = [_centre(R, t) for R, t in zip(fit2.R, fit2.t)]
    in_both = [c for c in used1 if c in used2]
    spans = [
        (np.linalg.norm(c1[c] - c1[in_both[0]]), np.linalg.norm(c2[c] - c2[in_both[0]])) for c in in_both[1:]
    ]
    scale = float(sum(s for _, s in spans) / sum(s for s, _ in spans) - 1) if spans else None
    halves = {
        "first": f"{keys[0]}-{keys[V // 2 - 1]}" if V > 1 else "-",
        "second": f"{keys[V // 2]}-{keys[-1]}",
        "first_on_second_px": _held_out(cal, obs, fit1, used1, second),
        "second_on_first_px": _held_out(cal, obs, fit2, used2, first),
        "rigs_apart": {
            n: (
                {
                    "centre_mm": float(np.linalg.norm(c1[c] - c2[c])),
                    "orientation_deg": _angle_deg(fit1.R[c] @ fit2.R[c].T),
                }
                if c in in_both
                else {"centre_mm": None, "orientation_deg": None}
            )
            for c, n in enumerate(names)
        },
        "scale_difference": scale,
    }
    known = cal.board.square_length
    every = _square(cal, cal.observations, a, list(range(len(cal.view_keys))), list(range(len(names))))
    held = [
        s
        for s in (_square(cal, obs, fit1, second, used1), _square(cal, obs, fit2, first, used2))
        if s is not None
    ]
    worst = max(held, key=lambda s: abs(s / known - 1)) if held else None
    square = {
        "known": known,
        "unit": unit,
        "all_frames": every,
        "held_out": worst,
        "all_frames_error": None if every is None else every / known - 1,
        "held_out_error": None if worst is None else worst / known - 1,
    }
    figures = {
        "detections": detections,
        "halves": halves,
        "square": square,
        "coverage": {r.name: r.coverage for r in cal.report},
        "bootstrap": _bootstrap(cal, resamples, seed),
        "frame_offsets": frame_offsets(cal),
    }
    return Report(figures, _warnings(figures, unit))


def _warnings(f: dict, unit: str) -> list[str]:
    out = []
    for name, o in f.get("frame_offsets", {}).items():
        if o["offset"] and o["px_at_0"] is not None and o["px"] < OFFSET_GAIN * o["px_at_0"]:
            out.append(
                f"camera {name}: its frame i shows the first camera's frame i{o['offset']:+d} "
                f"(the board fits it at {o['px']:.2f} px there, {o['px_at_0']:.2f} px as given): its "
                f"video is not synchronized; cut {abs(o['offset'])} frame(s) from the start of "
                + ("the other cameras' videos" if o["offset"] > 0 else f"camera {name}'s video")
                + " and calibrate again"
            )
    h = f["halves"]
    for name in f["detections"]:
        errs = [e for e in (h["first_on_second_px"][name], h["second_on_first_px"][name]) if e is not None]
        if not errs:
            out.append(
                f"camera {name} saw the board in fewer than {MIN_HALF_VIEWS} frames of one half "
                f"({h['first']} / {h['second']}): its calibration is not checked on held-out frames; "
                "record the board in its view throughout the recording"
            )
        elif max(errs) > HELD_OUT_MAX_PX:
            apart = h["rigs_apart"][name]["centre_mm"]
            out.append(
                f"camera {name}: the rig fitted on one half of the board frames puts the other half "
                f"{max(errs):.2f} px off (above {HELD_OUT_MAX_PX:g} px)"
                + (f", its centre {apart:.1f} {unit} apart between the halves" if apart is not None else "")
                + ": the board did not pin the rig down (or the camera moved); record more frames with the "
                "board tilted (30-60 degrees) at several depths across the shared volume, seen by several "
                "cameras at once"
            )
    sq = f["square"]
    for key, what in (("all_frames_error", "with the whole rig"), ("held_out_error", "held out")):
        if sq[key] is not None and abs(sq[key]) > SQUARE_MAX_ERROR:
            out.append(
                f"the board's square measures {sq[key] + 1:.4g} times its known {sq['known']:g} {unit} "
                f"({what}; {sq[key]:+.2%}, above {SQUARE_MAX_ERROR:.1%}): the scale is uncertain; check "
                "square_length against the printed board (--square-length) and record the board at "
                "more depths and tilts"
            )
            break
    if h["scale_difference"] is not None and abs(h["scale_difference"]) > SQUARE_MAX_ERROR:
        out.append(
            f"the two halves' rigs differ in scale by {h['scale_difference']:+.2%}: record more board "
            "frames, spread over the volume and over time"
        )
    for name, d in f["detections"].items():
        if d.get("views_dropped", 0) > DROPPED_MAX * max(d.get("board_frames", 0), 1):
            out.append(
                f"camera {name}: {d['views_dropped']} of its {d['board_frames']} board views were left out "
                "as wrong reads (they fit the rig much worse than the others): was the camera moved or "
                "knocked during the recording? Recalibrate from frames where it stood still"
            )
    for name, share in f["coverage"].items():
        if share < COVERAGE_MIN:
            out.append(
                f"camera {name}: the board covered {share:.0%} of its image (cells of an 8 x 8 grid; "
                f"below {COVERAGE_MIN:.0%}): its distortion is unconstrained at the edges; record the "
                "board near the edges and corners of its image"
            )
    return out


def report_path(out) -> Path:
    """Where the report goes beside a calibration: ``calibration.toml`` -> ``calibration.report.json``."""
    out = Path(out)
    return out.with_name(out.stem + ".report.json")
