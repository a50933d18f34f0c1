"""A whole rig from board detections (:func:`calibrate_detections`) or from board videos / image folders, one
per camera (:func:`calibrate_sources`): intrinsics per camera, extrinsics chained over the camera graph,
joint bundle adjustment; the world is the first camera or a chosen board view, the unit the board's."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.data.formats.anipose import units_from_board
from s3k.data.rig import Rig, check_camera_name
from s3k.geometry import Cameras, triangulate_pixels
from s3k.rigcal.boards import Board, Detections, Faces, check_board_matches, detect_board
from s3k.rigcal.bundle import Adjusted, bundle_adjust
from s3k.rigcal.solve import Intrinsics, Observations, chain_extrinsics, initial_intrinsics, relative_pose

COVERAGE_GRID = (8, 8)


@dataclass
class CameraReport:
    """One camera's figures after the adjustment (pixels)."""

    name: str
    views: int
    corners: int
    median_px: float
    rms_px: float
    coverage: float
    initial_rms_px: float
    dropped_views: int = 0


@dataclass
class RigCalibration:
    """The calibrated rig, its board, detections, the adjustment and the per-camera report."""

    names: list[str]
    sizes: list[tuple[int, int]]
    board: Board
    detections: list[Detections]
    adjusted: Adjusted
    observations: Observations
    view_keys: list[int]
    report: list[CameraReport]
    origin: str
    options: dict = field(default_factory=dict)

    def rig(self, units: str | None = None):
        """The result as a :class:`s3k.data.rig.Rig` (full resolution)."""

        a = self.adjusted
        cams = Cameras.from_numpy(
            np.stack([i.K() for i in a.intrinsics]),
            np.stack([i.dist() for i in a.intrinsics]),
            np.stack(a.R),
            np.stack(a.t),
            dtype=torch.float64,
        )
        return Rig(
            list(self.names),
            cams,
            np.asarray(self.sizes),
            units or units_from_board(self.board.square_length),
            {"board": self.board.describe(), "origin": self.origin},
        )

    def format(self) -> str:
        lines = [
            f"{'camera':<12}{'views':>6}{'corners':>9}{'median px':>11}{'rms px':>9}{'coverage':>10}"
            f"{'f px':>9}{'k1':>8}"
        ]
        for r, i in zip(self.report, self.adjusted.intrinsics):
            lines.append(
                f"{r.name:<12}{r.views:>6}{r.corners:>9}{r.median_px:>11.2f}{r.rms_px:>9.2f}"
                f"{r.coverage:>9.0%} {i.f:>8.1f}{i.k1:>8.3f}"
            )
        return "\n".join(lines)


def coverage(uv: np.ndarray, size: tuple[int, int], grid=COVERAGE_GRID) -> float:
    """Fraction of the cells of a ``grid`` over the image that hold a detected corner."""
    if not len(uv):
        return 0.0
    W, H = size
    gx = np.clip((uv[:, 0] / W * grid[0]).astype(int), 0, grid[0] - 1)
    gy = np.clip((uv[:, 1] / H * grid[1]).astype(int), 0, grid[1] - 1)
    return len(set(zip(gx.tolist(), gy.tolist()))) / (grid[0] * grid[1])


def _observations(detections: list[Detections], keys: list[int]) -> Observations:
    pos = {k: v for v, k in enumerate(keys)}
    cam, view, corner, uv = [], [], [], []
    for c, det in enumerate(detections):
        for k, (ids, pts) in det.frames.items():
            if k in pos:
                cam.append(np.full(len(ids), c))
                view.append(np.full(len(ids), pos[k]))
                corner.append(ids)
                uv.append(pts)
    return Observations(np.concatenate(cam), np.concatenate(view), np.concatenate(corner), np.concatenate(uv))


def _initial_views(keys, poses, R, t):
    """Each board view's board -> world pose from the camera that saw most of it... the first that saw it."""
    out = []
    for k in keys:
        for c in range(len(poses)):
            if k in poses[c]:
                Rb, tb = poses[c][k]  # board -> camera c
                out.append((R[c].T @ Rb, R[c].T @ (tb - t[c])))
                break
    return out


def calibrate_detections(
    names: list[str],
    detections: list[Detections],
    board: Board,
    *,
    free_principal_point: bool = False,
    radial: int = 2,
    origin_view: int | None = None,
    initial: list | None = None,
    fixed: list[int] | None = None,
    loss_scale_px: float = 1.0,
) -> RigCalibration:
    """A rig from each camera's board detections (see module doc).

    Args:
        names: camera names; ``detections`` one per camera, keyed by synchronized frame.
        board: the board (its square length sets the unit).
        free_principal_point: refine each camera's principal point (default: the image
            centre, anipose's model).
        radial: radial distortion terms, 1 (``k1``, anipose's model) or 2 (``k1, k2``).
        origin_view: a frame key whose board pose becomes the world frame (default: the first camera's frame).
        initial: ``[(Intrinsics, R, t) or None]`` per camera: known cameras (their pose gives the world).
        fixed: cameras of ``initial`` held fixed in the adjustment.
    """
    corners3d = (
        board.cv2_board().getChessboardCorners().astype(np.float64) if board.charuco else board.corners3d()
    )
    intr, poses, rms = [], [], []
    for c, (name, det) in enumerate(zip(names, detections)):
        if initial and initial[c] is not None:  # known intrinsics: the board's pose in each view by PnP
            i, p, r = initial[c][0], board_poses_pnp(det.frames, corners3d, initial[c][0]), float("nan")
        else:
            i, p, r = initial_intrinsics(name, det.frames, corners3d, det.size, free_principal_point, radial)
        intr.append(i)
        poses.append(p)
        rms.append(r)
    if initial and any(v is not None for v in initial):
        R, t = _place_unknown(names, initial, poses)
    else:
        extr = chain_extrinsics(names, poses)
        R, t = [e[0] for e in extr], [e[1] for e in extr]
    keys = sorted({k for p in poses for k in p})
    obs = _observations(
        [
            Detections({k: v for k, v in d.frames.items() if k in p}, d.size)
            for d, p in zip(detections, poses)
        ],
        keys,
    )
    adjust = functools.partial(bundle_adjust, fixed=fixed, free_principal_point=free_principal_point,
                               radial=radial, loss_scale_px=loss_scale_px)
    adj = adjust(intr, R, t, _initial_views(keys, poses, R, t), obs, corners3d)
    bad = _bad_views(obs, adj)
    # views left out per camera: by its own intrinsics' fit, then as wrong reads after the adjustment
    dropped = [sum(len(ids) >= 6 for ids, _ in d.frames.values()) - len(p)
               + len(set(obs.view[bad & (obs.cam == c)].tolist()))
               for c, (d, p) in enumerate(zip(detections, poses))]
    if bad.any():  # wrong detections (a grid read from the wrong corner): adjust again without them
        obs = _subset(obs, ~bad)
        adj = adjust(adj.intrinsics, adj.R, adj.t, adj.views, obs, corners3d)
    origin = "first camera" if not initial else "the fixed cameras"
    if origin_view is not None:
        if origin_view not in keys:
            raise UserError(
                f"--origin-view {origin_view}: no camera saw the board in that frame",
                hint=f"choose one of {', '.join(map(str, keys[:10]))}{'...' if len(keys) > 10 else ''}",
            )
        _move_world(adj, keys.index(origin_view))
        origin = f"board in frame {origin_view}"
    report = []
    for c, name in enumerate(names):
        sel = obs.cam == c
        err = np.linalg.norm(adj.residuals[sel], axis=1)
        report.append(
            CameraReport(
                name,
                len(set(obs.view[sel].tolist())),
                int(sel.sum()),
                float(np.median(err)),
                float(np.sqrt(np.mean(err**2))),
                coverage(obs.uv[sel], detections[c].size),
                rms[c],
                dropped[c],
            )
        )
    options = {"free_principal_point": free_principal_point, "radial": radial, "loss_scale_px": loss_scale_px,
               "fixed": fixed}
    return RigCalibration(
        list(names), [d.size for d in detections], board, detections, adj, obs, keys, report, origin, options
    )


BAD_VIEW_PX = 5.0  # a camera's view of the board whose median residual exceeds this is a wrong detection


def _bad_views(obs: Observations, adj: Adjusted) -> np.ndarray:
    """``(n,)`` bool: the observations of the (camera, board view) pairs whose median residual exceeds
    ``max(BAD_VIEW_PX, 10 x the median residual)``."""
    err = np.linalg.norm(adj.residuals, axis=1)
    limit = max(BAD_VIEW_PX, 10 * float(np.median(err)))
    bad = np.zeros(len(err), bool)
    for c, v in set(zip(obs.cam.tolist(), obs.view.tolist())):
        sel = (obs.cam == c) & (obs.view == v)
        if np.median(err[sel]) > limit:
            bad |= sel
    return bad


def _subset(obs: Observations, keep: np.ndarray) -> Observations:
    return Observations(
        obs.cam[keep], obs.view[keep], obs.corner[keep], obs.uv[keep], obs.pcam, obs.ppoint, obs.puv
    )


def board_poses_pnp(frames: dict, corners3d: np.ndarray, intr: Intrinsics) -> dict:
    """The board's pose ``(R, t)`` (board -> camera) in each view of a camera with known intrinsics."""

    out = {}
    for k, (ids, pts) in frames.items():
        if len(ids) < 6:
            continue
        ok, rvec, tvec = cv2.solvePnP(corners3d[ids], pts, intr.K(), intr.dist())
        if ok:
            out[k] = (cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    return out


def _place_unknown(names, initial, poses):
    """Cameras of ``initial`` as given; each other camera placed from board views it shares with a known
    one."""

    R: list = [None] * len(names)
    t: list = [None] * len(names)
    for c, v in enumerate(initial):
        if v is not None:
            R[c], t[c] = v[1], v[2]
    for c in range(len(names)):
        if R[c] is not None:
            continue
        best = max(
            ((len(set(poses[a]) & set(poses[c])), a) for a in range(len(names)) if initial[a] is not None),
            default=(0, -1),
        )
        if best[0] < 1:
            raise UserError(
                f"camera {names[c]} shares no board view with the cameras kept "
                f"({', '.join(n for n, v in zip(names, initial) if v is not None)})",
                hint="record frames where the board is seen by it and by one of them",
            )
        a = best[1]
        R_ab, t_ab = relative_pose(poses[a], poses[c], sorted(set(poses[a]) & set(poses[c])))
        R[c], t[c] = R_ab.T @ R[a], R_ab.T @ (t[a] - t_ab)
    return R, t


def _move_world(adj: Adjusted, v: int) -> None:
    """Make board view ``v``'s frame the world: ``x_c = R_c (R_v x_b + t_v) + t_c``."""
    Rv, tv = adj.views[v]
    adj.t = [Rc @ tv + tc for Rc, tc in zip(adj.R, adj.t)]
    adj.R = [Rc @ Rv for Rc in adj.R]
    adj.views = [(Rv.T @ R, Rv.T @ (t - tv)) for R, t in adj.views]
    if len(adj.points):
        adj.points = (adj.points - tv) @ Rv


def _same_views(names: list[str], detections: list[Detections]) -> list[list[str]]:
    """Groups of two or more cameras whose board detections are identical (the same images given for each)."""
    groups: list[list[int]] = []
    for c, det in enumerate(detections):
        for group in groups:
            other = detections[group[0]].frames
            if other.keys() == det.frames.keys() and all(
                np.array_equal(other[k][0], v[0]) and np.array_equal(other[k][1], v[1])
                for k, v in det.frames.items()
            ):
                group.append(c)
                break
        else:
            groups.append([c])
    return [[names[c] for c in g] for g in groups if len(g) > 1]


def _refuse_same_views(groups: list[list[str]], what: str) -> None:
    if groups:
        raise UserError(
            f"cameras {', '.join(groups[0])} {what}: they would be calibrated as one camera "
            "in the same place" + (f" (and {len(groups) - 1} more such group(s))" if len(groups) > 1 else ""),
            hint="give each camera its own recording, or pass --allow-identical-views",
        )


def calibrate_sources(sources: dict[str, str], board: Board, *, every: int = 1, identical: bool = False,
                      faces: Faces | None = None, **options) -> RigCalibration:
    """Detect the board in each camera's video or image folder (frames synchronized by index or by the number
    in the file names), then :func:`calibrate_detections`. Cameras given the same source, or whose
    detections are identical, are refused unless ``identical``."""
    names = [check_camera_name(name, "CAM=SOURCE") for name in sources]
    if not identical:
        same: dict[str, list[str]] = {}
        for name in names:
            same.setdefault(str(Path(sources[name]).resolve()), []).append(name)
        _refuse_same_views([g for g in same.values() if len(g) > 1], "are given the same source")
    detections = []
    for name in names:
        det = detect_board(sources[name], board, every=every, faces=faces)
        check_board_matches(name, sources[name], det, board)
        detections.append(det)
    if not identical:
        _refuse_same_views(_same_views(names, detections), "show identical board views")
    return calibrate_detections(names, detections, board, **options)


def intrinsics_of(K: np.ndarray, dist: np.ndarray) -> Intrinsics:
    return Intrinsics(float(K[0, 0]), float(K[0, 2]), float(K[1, 2]), float(dist[0]), float(dist[1]))


def refine_with_points(
    cal: RigCalibration,
    uv: np.ndarray,
    *,
    radial: int = 2,
    free_principal_point: bool = False,
    loss_scale_px: float = 1.0,
) -> RigCalibration:
    """Adjust the rig again with extra correspondences: ``uv (T, C, K, 2)`` pixels (NaN where not seen) of
    points seen by several cameras at once (labelled keypoints), each (frame, keypoint) seen by >= 2 cameras a
    3D point of the adjustment, started from its triangulation with the board-only rig."""

    seen = np.isfinite(uv).all(-1)  # (T, C, K)
    X, valid = triangulate_pixels(
        cal.rig().cameras, torch.from_numpy(np.nan_to_num(uv)), torch.from_numpy(seen * 1.0)
    )
    use = valid.numpy() & (seen.sum(1) >= 2)  # (T, K)
    frames, kps = np.nonzero(use)
    if not len(frames):
        raise UserError("the labels give no keypoint seen by two cameras in one frame; nothing to add")
    points = X.numpy()[frames, kps]
    pcam, ppoint, puv = [], [], []
    for p, (f, k) in enumerate(zip(frames, kps)):
        for c in np.flatnonzero(seen[f, :, k]):
            pcam.append(c)
            ppoint.append(p)
            puv.append(uv[f, c, k])
    o = cal.observations
    obs = Observations(o.cam, o.view, o.corner, o.uv, np.asarray(pcam), np.asarray(ppoint), np.asarray(puv))
    a = cal.adjusted
    corners3d = (
        cal.board.cv2_board().getChessboardCorners().astype(np.float64)
        if cal.board.charuco
        else cal.board.corners3d()
    )
    adj = bundle_adjust(
        a.intrinsics,
        a.R,
        a.t,
        a.views,
        obs,
        corners3d,
        points=points,
        free_principal_point=free_principal_point,
        radial=radial,
        loss_scale_px=loss_scale_px,
    )
    report = []
    for i, r in enumerate(cal.report):
        sel = obs.cam == i
        err = np.linalg.norm(adj.residuals[sel], axis=1)
        report.append(
            CameraReport(
                r.name,
                r.views,
                r.corners,
                float(np.median(err)),
                float(np.sqrt(np.mean(err**2))),
                r.coverage,
                r.initial_rms_px,
                r.dropped_views,
            )
        )
    return RigCalibration(
        cal.names,
        cal.sizes,
        cal.board,
        cal.detections,
        adj,
        obs,
        cal.view_keys,
        report,
        cal.origin + f", with {len(points)} labelled points",
        cal.options,
    )
