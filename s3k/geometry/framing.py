"""Where a 3D viewer should look at a rig's work, pure numpy (no viewer): the table's (or floor's) normal as
the scene's up, the object's centre and a distance that frames it.

Cameras are OpenCV's (``x_cam = R x_world + t``): a camera's viewing direction in the world is ``R[2]``, its
centre ``-R^T t``. A rig looks down at its work, so the up estimate starts from the cameras: the opposite of
their mean viewing direction (:func:`cameras_up`; where they face each other across the work, the mean of
their images' up), or, where the cameras are level (their x axes, the images' rows, all nearly perpendicular
to one direction: :data:`LEVEL`, within :data:`LEVEL_MAX_ANGLE` degrees of the mean's), that direction, which
does not lean towards the side most cameras stand on. Where 3D points of the object are given and spread flat
(a moving object on a table: their smallest spread well below the middle one), the normal of the plane fitted
to them, turned to face the cameras, is the better estimate, and is taken when it lies within
:data:`PLANE_MAX_ANGLE` degrees of the cameras' (a plane further off is a wall or the object itself, not the
table).

:func:`frame` gives the whole :class:`Framing`: the rotation that turns the up onto +Z with the object's
centre at the origin (the display's coordinates), the radius that holds the points (a few far outliers
aside), and an eye at a distance from which a view of ``fov_y`` degrees sees all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Framing", "camera_centres", "cameras_up", "fitted_plane", "frame", "look_at_point",
           "rotation_onto_z", "up_direction", "viewing_directions"]

LOOK_DOWN = 0.2
"""Below this length of their mean viewing direction the cameras face each other and say no down."""
LEVEL = 0.05
"""The cameras are level where the x axes' smallest second moment is below this share of the middle one."""
LEVEL_MAX_ANGLE = 60.0
"""Degrees: the level cameras' up is taken only within this angle of the mean viewing direction's."""
PLANE_MAX_ANGLE = 45.0
"""Degrees: the fitted plane's normal is the up only within this angle of the cameras' estimate."""
FLAT = 0.5
"""The points' smallest spread over their middle one below which they lie on a plane."""
OUTLIER = 4.0
"""Points further from the centre than this many times the 90th percentile distance are not framed."""
DEFAULT_FOV_Y = 55.0
"""Degrees: the vertical field of view of Rerun's 3D eye."""


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _rotations(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotations of shape (C, 3, 3) expected, got {R.shape}")
    return R.reshape(-1, 3, 3)


def viewing_directions(R: np.ndarray) -> np.ndarray:
    """``(C, 3)``: each camera's optical axis (its +z) in the world, from its rotations ``R (C, 3, 3)``."""
    return _rotations(R)[:, 2].copy()


def camera_centres(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(C, 3)``: each camera's centre ``-R^T t`` in the world."""
    return -np.einsum("cji,cj->ci", _rotations(R), np.asarray(t, dtype=np.float64).reshape(-1, 3))


def look_at_point(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(3,)``: the point nearest (least squares) to the cameras' optical axes; the mean of their centres
    where the axes do not meet (one camera, parallel axes)."""
    d, c = viewing_directions(R), camera_centres(R, t)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projections onto each axis's normal plane
    A, b = P.sum(0), np.einsum("cij,cj->i", P, c)
    if np.linalg.cond(A) > 1e8:
        return c.mean(0)
    return np.linalg.solve(A, b)


def fitted_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(centre (3,), normal (3,), flatness)`` of the plane fitted to the finite rows of ``points (N, 3)``
    (least squares; flatness: the smallest spread over the middle one, 0 for coplanar points); ``None`` with
    fewer than three points or where they lie on a line."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(-1)]
    if len(P) < 3:
        return None
    centre = P.mean(0)
    _, s, vt = np.linalg.svd(P - centre, full_matrices=False)
    if s[1] <= 1e-12 * max(s[0], 1e-300):
        return None
    return centre, vt[2], float(s[2] / s[1])


def _within(a: np.ndarray, b: np.ndarray, degrees: float) -> bool:
    return bool(np.degrees(np.arccos(np.clip(a @ b, -1, 1))) <= degrees)


def cameras_up(R: np.ndarray) -> np.ndarray:
    """``(3,)`` unit: the up the cameras alone give (module docstring): the direction their x axes are all
    perpendicular to where they are level, else the opposite of their mean viewing direction (where they face
    each other, :data:`LOOK_DOWN`: the mean of their images' up)."""
    mean = viewing_directions(R).mean(0)
    if np.linalg.norm(mean) >= LOOK_DOWN:
        up = -_unit(mean)
    else:  # cameras facing each other across the work: their images' up, else the world's +Z
        image_up = -_rotations(R)[:, 1].mean(0)
        up = _unit(image_up) if np.linalg.norm(image_up) > 1e-9 else np.array([0.0, 0.0, 1.0])
    x = _rotations(R)[:, 0]
    w, v = np.linalg.eigh(x.T @ x)
    if w[0] < LEVEL * w[1]:
        level = v[:, 0] if v[:, 0] @ up >= 0 else -v[:, 0]
        if _within(level, up, LEVEL_MAX_ANGLE):
            return level
    return up


def up_direction(R: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """``(3,)`` unit: the table's normal, pointing towards the cameras (module docstring): the plane fitted to
    ``points (N, 3)`` where they spread flat and agree with the cameras, else :func:`cameras_up`."""
    up = cameras_up(R)
    plane = fitted_plane(points) if points is not None else None
    if plane is not None and plane[2] < FLAT:
        normal = plane[1] if plane[1] @ up >= 0 else -plane[1]
        if _within(normal, up, PLANE_MAX_ANGLE):
            return normal
    return up


def rotation_onto_z(up: np.ndarray) -> np.ndarray:
    """``(3, 3)``: the smallest proper rotation ``Q`` with ``Q @ up = (0, 0, 1)``."""
    u = _unit(np.asarray(up, dtype=np.float64))
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(u, z), float(u @ z)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])  # half a turn about x
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + V + V @ V / (1 + c)


@dataclass(frozen=True)
class Framing:
    """A 3D view of the work. ``up`` (world, unit) the table's normal; ``centre`` (world) the object's
    centre; ``rotation`` and ``translation`` take the world to the display (``rotation @ x + translation``:
    the up along +Z, the centre at the origin); ``radius`` holds the framed points; ``eye`` (display) a
    position that sees the ball of ``radius`` around the origin, looking at it with +Z up."""

    up: np.ndarray
    centre: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    radius: float
    eye: np.ndarray

    def to_display(self, X: np.ndarray) -> np.ndarray:
        """World points ``(..., 3)`` in the display's coordinates."""
        return np.asarray(X, dtype=np.float64) @ self.rotation.T + self.translation


def _framed_points(points: np.ndarray | None) -> np.ndarray:
    if points is None:
        return np.zeros((0, 3))
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return P[np.isfinite(P).all(-1)]


def frame(R: np.ndarray, t: np.ndarray, points: np.ndarray | None = None, fov_y: float = DEFAULT_FOV_Y,
          elevation: float = 35.0, margin: float = 1.1) -> Framing:
    """The :class:`Framing` of a rig (``R (C, 3, 3)``, ``t (C, 3)``) and the object's ``points (..., 3)``
    (NaN rows ignored): the centre the points' median (without points: where the cameras look, the radius
    then holding the cameras), the radius the largest distance from it (points more than :data:`OUTLIER`
    times the 90th percentile distance away left out), the eye ``margin`` times the distance at which the
    ball fits a view of ``fov_y`` degrees, ``elevation`` degrees above the table on the cameras' side."""
    centres = camera_centres(R, t)
    P = _framed_points(points)
    up = up_direction(R, P if len(P) else None)
    if len(P):
        centre = np.median(P, axis=0)
        dist = np.linalg.norm(P - centre, axis=-1)
        radius = float(dist[dist <= OUTLIER * np.percentile(dist, 90)].max())
    else:
        centre = look_at_point(R, t)
        radius = float(np.linalg.norm(centres - centre, axis=-1).max())
    # a single point (or points at one place) is framed like a small part of the rig
    radius = max(radius, 0.05 * float(np.median(np.linalg.norm(centres - centre, axis=-1))), 1e-9)
    Q = rotation_onto_z(up)
    translation = -Q @ centre
    heading = (centres.mean(0) - centre) @ Q.T
    heading[2] = 0.0
    if np.linalg.norm(heading) < 1e-6 * radius:  # cameras all around: the first camera's side
        heading = (centres[0] - centre) @ Q.T
        heading[2] = 0.0
    if np.linalg.norm(heading) < 1e-6 * radius:  # straight above: any side
        heading = np.array([1.0, 0.0, 0.0])
    e = np.radians(elevation)
    direction = np.cos(e) * _unit(heading) + np.sin(e) * np.array([0.0, 0.0, 1.0])
    distance = margin * radius / np.sin(np.radians(fov_y) / 2)
    return Framing(up=up, centre=centre, rotation=Q, translation=translation, radius=radius,
                   eye=distance * direction)
