"""Each camera's frame offset from the board's motion during calibration, against the first camera: the
board's pose in each camera's frames (PnP with the calibrated intrinsics), and for each shift of a few
frames the relative pose of the two cameras averaged over the frames they pair up (as :func:`relative_pose`
does for the rig) and the camera's corners predicted from the first camera's board poses through it; the
shift with the smallest median error gives the camera's offset ``N``, in the convention of
:mod:`s3k.data.sync` and ``s3k import --frame-offsets CAM=N``: its frame ``i`` shows the instant of the first
camera's frame ``i + N``. Needs no synchronized rig, so a camera out of sync does not bias the
others. Meaningful for videos filmed continuously while the board moved; in image folders of separate board
positions a shift jumps to another position, and the offset found is 0 whatever the clocks did.
"""

from __future__ import annotations

import numpy as np

from s3k.rigcal.rig import RigCalibration, board_poses_pnp
from s3k.rigcal.solve import project, relative_pose

MAX_OFFSET = 3
"""Frames tried either way."""
MIN_PAIRED = 3
"""Frames two cameras must pair up at a shift for it to be measured."""


def _corners3d(cal: RigCalibration) -> np.ndarray:
    b = cal.board
    return b.cv2_board().getChessboardCorners().astype(np.float64) if b.charuco else b.corners3d()


def frame_offsets(cal: RigCalibration, max_offset: int = MAX_OFFSET) -> dict[str, dict]:
    """Per camera ``{"offset": frames, "px": median error there, "px_at_0": median error unshifted}`` against
    the first camera (``offset`` None where no shift pairs :data:`MIN_PAIRED` frames)."""
    corners3d, a = _corners3d(cal), cal.adjusted
    poses = [board_poses_pnp(d.frames, corners3d, i) for d, i in zip(cal.detections, a.intrinsics)]
    out: dict[str, dict] = {}
    for c, name in enumerate(cal.names):
        i = a.intrinsics[c]
        errors: dict[int, float] = {}
        for d in range(-max_offset, max_offset + 1) if c else [0]:
            shifted = {
                k - d: p for k, p in poses[c].items()
            }  # the first camera's frame k <-> c's frame k + d
            paired = sorted(set(poses[0]) & set(shifted))
            if len(paired) < MIN_PAIRED:
                continue
            R, t = relative_pose(shifted, poses[0], paired)  # x_c = R x_0 + t
            err = []
            for k in paired:
                Rb, tb = poses[0][k]
                ids, uv = cal.detections[c].frames[k + d]
                Xc = (corners3d[ids] @ Rb.T + tb) @ R.T + t
                err.append(np.linalg.norm(project(Xc, i.f, i.cx, i.cy, i.k1, i.k2) - uv, axis=1))
            errors[d] = float(np.median(np.concatenate(err)))
        best = min(errors, key=lambda d: (errors[d], abs(d))) if errors else None
        out[name] = {"offset": None if best is None else -best, "px": None if best is None else errors[best],
                     "px_at_0": errors.get(0)}
    return out
