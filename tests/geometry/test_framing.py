"""The 3D view's framing (:mod:`s3k.geometry.framing`, pure numpy): the table's normal recovered from a rig
looking down at it, whatever the world's orientation, and an eye that sees every point of the object."""

from __future__ import annotations

import numpy as np
import pytest

from s3k.geometry.framing import (
    DEFAULT_FOV_Y,
    camera_centres,
    cameras_up,
    fitted_plane,
    frame,
    look_at_point,
    rotation_onto_z,
    up_direction,
    viewing_directions,
)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _look_at(centre: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """The world-to-camera rotation of a camera at ``centre`` looking at ``target``, its x axis level (rolled
    by ``roll`` degrees), z up in the table's frame."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    a = np.radians(roll)
    x, y = np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y
    return np.stack([x, y, z])


def _rig(azimuths, elevations, rng, distance=1.0, roll=5.0):
    """Cameras around a table (its normal +Z, its centre at the origin) looking down near its centre, each
    rolled by up to ``roll`` degrees: ``(R (C, 3, 3), t (C, 3))``."""
    Rs, ts = [], []
    for az, el in zip(azimuths, elevations):
        a, e = np.radians(az), np.radians(el)
        centre = distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        R = _look_at(centre, rng.uniform(-0.05, 0.05, 3) * [1, 1, 0], roll=rng.uniform(-roll, roll))
        Rs.append(R)
        ts.append(-R @ centre)
    return np.array(Rs), np.array(ts)


def _moved(R, t, points, G, s):
    """The rig and the points in a world turned by ``G`` and moved by ``s`` (``x' = G x + s``)."""
    R2 = R @ G.T
    t2 = t - np.einsum("cij,j->ci", R2, s)
    return R2, t2, None if points is None else points @ G.T + s


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _table_points(rng, n=200, height=0.03):
    """An object moving on the table: points over 30 cm of it, up to ``height`` above it."""
    return np.column_stack([rng.uniform(-0.15, 0.15, n), rng.uniform(-0.15, 0.15, n),
                            rng.uniform(0, height, n)])


@pytest.mark.parametrize("seed", range(5))
def test_the_up_of_cameras_around_a_table_is_its_normal_whatever_the_worlds_orientation(seed):
    rng = np.random.default_rng(seed)
    R, t = _rig([10, 95, 170, 240, 310], rng.uniform(35, 65, 5), rng)
    G, s = _random_rotation(rng), rng.normal(size=3)
    R2, t2, _ = _moved(R, t, None, G, s)
    normal = G @ [0, 0, 1]
    # the rig as the world sees it: cameras up in the air, looking at the table's centre
    np.testing.assert_allclose(camera_centres(R2, t2), (camera_centres(R, t) @ G.T) + s, atol=1e-9)
    np.testing.assert_allclose(look_at_point(R2, t2), s, atol=0.1)
    assert _angle(up_direction(R2), normal) < 3  # level cameras: their rows are horizontal
    # the points on the table say the same
    points = _table_points(rng) @ G.T + s
    assert _angle(up_direction(R2, points), normal) < 2
    # cameras rolled every way: their mean viewing direction, near the normal for a ring around the table
    R, t = _rig(rng.uniform(-10, 10) + np.arange(0, 360, 72), rng.uniform(45, 55, 5), rng, roll=90)
    R2, t2, _ = _moved(R, t, None, G, s)
    mean = viewing_directions(R2).mean(0)
    np.testing.assert_allclose(cameras_up(R2), -mean / np.linalg.norm(mean))
    assert _angle(up_direction(R2), normal) < 5


def test_points_spread_on_the_table_correct_a_rig_on_one_side():
    rng = np.random.default_rng(7)
    # every camera on one side of the table, rolled every way
    R, t = _rig([0, 40, 80, 120], [30, 45, 60, 35], rng, roll=90)
    G, s = _random_rotation(rng), rng.normal(size=3)
    R2, t2, points = _moved(R, t, _table_points(rng), G, s)
    normal = G @ [0, 0, 1]
    assert _angle(up_direction(R2), normal) > 10  # the mean viewing direction leans away from the cameras
    assert _angle(up_direction(R2, points), normal) < 2
    # the same rig with level cameras knows the table from the cameras alone
    level, _ = _rig([0, 40, 80, 120], [30, 45, 60, 35], rng)
    assert _angle(-viewing_directions(level).mean(0), [0, 0, 1]) > 10
    assert _angle(cameras_up(level @ G.T), normal) < 3
    # a blob of points (an object that did not move) has no plane: the cameras' estimate stands
    blob = rng.normal(size=(100, 3)) * 0.05 + s
    np.testing.assert_allclose(up_direction(R2, blob), up_direction(R2), atol=1e-12)
    # a flat spread far from level (a wall, or the object standing up) is not taken for the table either
    wall = _table_points(rng)[:, [2, 1, 0]] @ G.T + s
    np.testing.assert_allclose(up_direction(R2, wall), up_direction(R2), atol=1e-12)
    # NaN rows are ignored; the plane's normal faces the cameras whatever its sign from the fit
    with_nan = np.vstack([points, np.full((5, 3), np.nan)])
    assert _angle(up_direction(R2, with_nan), normal) < 2
    centre, n, flatness = fitted_plane(points)
    assert flatness < 0.2 and _angle(abs(n @ normal) * normal, normal) < 2
    assert fitted_plane(points[:2]) is None and fitted_plane(np.outer(np.arange(5.0), [1, 2, 3])) is None


def test_rotation_onto_z_turns_the_up_onto_z():
    rng = np.random.default_rng(1)
    for up in [*rng.normal(size=(5, 3)), np.array([0, 0, 3.0]), np.array([0, 0, -2.0]),
               np.array([0, 1e-9, -1])]:
        Q = rotation_onto_z(up)
        np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(Q) == pytest.approx(1.0)
        np.testing.assert_allclose(Q @ (up / np.linalg.norm(up)), [0, 0, 1], atol=1e-7)


def _in_view(framing, X, fov_y=DEFAULT_FOV_Y) -> np.ndarray:
    """Whether each world point lies within the eye's cone of ``fov_y`` degrees around its line of sight."""
    d = framing.to_display(X) - framing.eye
    axis = -framing.eye / np.linalg.norm(framing.eye)
    return d @ axis / np.linalg.norm(d, axis=-1) >= np.cos(np.radians(fov_y) / 2)


def test_the_eye_frames_every_point_on_the_table_seen_from_above():
    rng = np.random.default_rng(3)
    R, t = _rig([0, 90, 180, 270], [45, 50, 55, 60], rng)
    G, s = _random_rotation(rng), rng.normal(size=3)
    R2, t2, points = _moved(R, t, _table_points(rng) * [3, 1, 1] + [0.2, 0, 0], G, s)
    f = frame(R2, t2, points)
    np.testing.assert_allclose(f.to_display(np.median(points, 0)), 0, atol=1e-9)  # the centre at the origin
    np.testing.assert_allclose(f.rotation @ f.up, [0, 0, 1], atol=1e-9)  # the up along +Z
    np.testing.assert_allclose(f.radius, np.linalg.norm(points - np.median(points, 0), axis=-1).max())
    assert _in_view(f, points).all()
    assert f.eye[2] > 0  # above the table
    assert (f.to_display(camera_centres(R2, t2))[:, 2] > 0).all()  # the cameras too
    # no nearer: at 90 % of the distance the farthest points fall out of a view of the same angle
    nearer = type(f)(f.up, f.centre, f.rotation, f.translation, f.radius, f.eye * 0.8)
    assert not _in_view(nearer, points).all()


def test_a_far_outlier_is_not_framed_and_cameras_alone_frame_the_rig():
    rng = np.random.default_rng(4)
    R, t = _rig([0, 120, 240], [40, 50, 60], rng)
    points = _table_points(rng)
    with_outlier = np.vstack([points, [[50.0, 0, 0]], np.full((3, 3), np.nan)])
    f = frame(R, t, with_outlier)
    assert f.radius < 0.5 and _in_view(f, points).all() and not _in_view(f, with_outlier[-4:-3]).any()
    # without points: the centre is where the cameras look and the view holds the cameras
    bare = frame(R, t)
    np.testing.assert_allclose(bare.centre, look_at_point(R, t))
    assert _in_view(bare, camera_centres(R, t)).all()
    np.testing.assert_allclose(bare.up, cameras_up(R))
    # one point: framed as a small part of the rig, not from zero distance
    one = frame(R, t, points[:1])
    assert one.radius > 0 and np.linalg.norm(one.eye) > 0.05


def test_cameras_facing_each_other_across_the_work_stand_on_their_images_up():
    rng = np.random.default_rng(5)
    G = _random_rotation(rng)
    # two level cameras at the work's height, looking at it from opposite sides: no down to average
    R, t = _rig([0, 180], [0, 0], rng, roll=0)
    np.testing.assert_allclose(viewing_directions(R).sum(0)[:2], 0, atol=0.1)
    assert _angle(cameras_up(R @ G.T), G @ [0, 0, 1]) < 3
    # three rolled a little: not level, their images' up still is
    R, t = _rig([0, 120, 240], [0, 0, 0], rng, roll=20)
    R2, t2, _ = _moved(R, t, None, G, np.zeros(3))
    assert _angle(cameras_up(R2), G @ [0, 0, 1]) < 20
    f = frame(R2, t2)
    assert np.isfinite(f.eye).all() and f.radius > 0
