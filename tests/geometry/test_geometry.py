"""Tests for s3k.geometry: camera model against OpenCV, rays, rotations, weighted triangulation."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from s3k.geometry import (
    Cameras,
    camera_centres,
    distort,
    matrix_to_rodrigues,
    pixel_rays,
    project,
    rodrigues_to_matrix,
    triangulate_pixels,
    triangulate_rays,
    undistort,
    undistort_pixels,
)

F64 = torch.float64
# OpenCV's undistortPoints defaults to 5 fixed-point iterations, which is not converged for strong
# distortion; the reference is OpenCV's own iteration run to convergence.
CV_CONVERGED = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-15)


def look_at_R(centre: np.ndarray, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """World->camera rotation of a camera at ``centre`` whose optical axis (+z) points at ``target``."""
    z = target - centre
    z /= np.linalg.norm(z)
    up = rng.normal(size=3)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def random_rig(lead: tuple[int, ...], seed: int, skew: bool = False, strong: bool = False) -> dict:
    """Cameras about 1 m from the origin looking at it, with realistic distortion, as float64 arrays."""
    rng = np.random.default_rng(seed)
    n = int(np.prod(lead, dtype=np.int64))
    K = np.zeros((n, 3, 3))
    R = np.zeros((n, 3, 3))
    t = np.zeros((n, 3))
    dist = np.zeros((n, 5))
    for i in range(n):
        f = rng.uniform(300, 700)
        K[i] = [
            [f, rng.uniform(-2, 2) if skew else 0.0, rng.uniform(150, 250)],
            [0, f * rng.uniform(0.95, 1.05), rng.uniform(150, 250)],
            [0, 0, 1],
        ]
        centre = rng.normal(size=3)
        centre *= rng.uniform(0.8, 1.2) / np.linalg.norm(centre)
        R[i] = look_at_R(centre, rng.normal(size=3) * 0.05, rng)
        t[i] = -R[i] @ centre
        s = 2.0 if strong else 1.0
        dist[i] = [
            rng.uniform(-0.3, 0.1) * s,
            rng.uniform(-0.1, 0.1) * s,
            rng.uniform(-2e-3, 2e-3) * s,
            rng.uniform(-2e-3, 2e-3) * s,
            rng.uniform(-0.02, 0.02) * s,
        ]
    return {
        "K": K.reshape(lead + (3, 3)),
        "dist": dist.reshape(lead + (5,)),
        "R": R.reshape(lead + (3, 3)),
        "t": t.reshape(lead + (3,)),
    }


def cams_of(rig: dict, dtype: torch.dtype = F64) -> Cameras:
    return Cameras.from_numpy(rig["K"], rig["dist"], rig["R"], rig["t"], dtype=dtype)


def workspace_points(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.15, 0.15, size=(n, 3))


# ----------------------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------------------


def test_cameras_shape_index_to_and_numpy_round_trip():
    rig = random_rig((2, 3), seed=0)
    cams = cams_of(rig)
    assert cams.shape == (2, 3) and len(cams) == 2 and cams.dtype == F64
    sub = cams[:, 1]
    assert sub.shape == (2,)
    torch.testing.assert_close(sub.K, torch.as_tensor(rig["K"][:, 1]))
    assert cams[1, 2].shape == ()
    assert cams.to(torch.float32).dtype == torch.float32
    back = cams.numpy()
    for name in ("K", "dist", "R", "t"):
        np.testing.assert_array_equal(back[name], rig[name])
    torch.testing.assert_close(cams.reshape(6).R, cams.R.reshape(6, 3, 3))
    with pytest.raises(ValueError, match="too many indices"):
        cams[0, 0, 0]


def test_cameras_broadcast_shared_fields_and_default_dist():
    R = rodrigues_to_matrix(torch.randn(4, 3, dtype=F64))
    cams = Cameras(torch.eye(3, dtype=F64), None, R, torch.zeros(4, 3, dtype=F64))
    assert cams.shape == (4,) and cams.K.shape == (4, 3, 3) and cams.dist.shape == (4, 5)
    assert torch.all(cams.dist == 0)


def test_cameras_from_numpy_accepts_opencv_shapes():
    rng = np.random.default_rng(1)
    rvec = rng.normal(size=(3, 1))
    tvec = rng.normal(size=(3, 1))
    K = np.array([[400.0, 0, 100], [0, 410, 90], [0, 0, 1]])
    cams = Cameras.from_numpy(K, np.array([[0.1, -0.02, 1e-3, 2e-3]]), rvec, tvec, dtype=F64)
    np.testing.assert_allclose(cams.R.numpy(), cv2.Rodrigues(rvec)[0], atol=1e-12)
    np.testing.assert_allclose(cams.t.numpy(), tvec[:, 0])
    np.testing.assert_allclose(cams.dist.numpy(), [0.1, -0.02, 1e-3, 2e-3, 0])
    # three cameras given by Rodrigues vectors: (3, 3) like t, not one matrix
    rvecs = rng.normal(size=(3, 3))
    three = Cameras.from_numpy(np.stack([K] * 3), None, rvecs, rng.normal(size=(3, 3)), dtype=F64)
    assert three.shape == (3,)
    np.testing.assert_allclose(three.R[1].numpy(), cv2.Rodrigues(rvecs[1])[0], atol=1e-12)
    with pytest.raises(ValueError, match="rational"):
        Cameras.from_numpy(K, np.r_[np.zeros(5), 0.1, 0, 0], rvec, tvec)


def test_cameras_shape_errors_name_the_field():
    eye = torch.eye(3)
    with pytest.raises(ValueError, match=r"Cameras\.K"):
        Cameras(torch.eye(4), None, eye, torch.zeros(3))
    with pytest.raises(ValueError, match=r"Cameras\.t"):
        Cameras(eye, None, eye, torch.zeros(4))
    with pytest.raises(ValueError, match=r"Cameras\.dist"):
        Cameras(eye, torch.zeros(4), eye, torch.zeros(3))
    with pytest.raises(ValueError, match="broadcast"):
        Cameras(eye.expand(2, 3, 3), None, eye.expand(3, 3, 3), torch.zeros(3))
    with pytest.raises(ValueError, match="dtype"):
        Cameras(eye, None, eye.double(), torch.zeros(3))


def test_camera_centres_map_to_camera_origin():
    cams = cams_of(random_rig((5,), seed=2))
    a = camera_centres(cams)
    torch.testing.assert_close(cams.centres(), a)
    x_cam = (cams.R @ a[..., None])[..., 0] + cams.t
    torch.testing.assert_close(x_cam, torch.zeros_like(x_cam), atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------------------------------------
# Projection and distortion against OpenCV
# ----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lead", [(), (3,), (2, 3)])
def test_project_matches_opencv(lead):
    rig = random_rig(lead, seed=10 + len(lead), strong=True)
    cams = cams_of(rig)
    X = workspace_points(40, seed=3)
    uv, depth = project(cams, torch.as_tensor(X))
    assert uv.shape == lead + (40, 2) and depth.shape == lead + (40,)
    flat = {k: v.reshape((-1,) + v.shape[len(lead) :]) for k, v in rig.items()}
    uv_flat = uv.reshape(-1, 40, 2).numpy()
    for i in range(len(flat["K"])):
        rvec = cv2.Rodrigues(flat["R"][i])[0]
        ref, _ = cv2.projectPoints(X, rvec, flat["t"][i], flat["K"][i], flat["dist"][i])
        np.testing.assert_allclose(uv_flat[i], ref[:, 0], atol=1e-4, rtol=0)
        np.testing.assert_allclose(
            depth.reshape(-1, 40)[i].numpy(), (X @ flat["R"][i].T + flat["t"][i])[:, 2]
        )


def test_project_with_skew_uses_the_full_K():
    # OpenCV ignores K[0, 1]; the model here keeps it so that warps K <- M K stay exact.
    rig = random_rig((2,), seed=4, skew=True)
    cams = cams_of(rig)
    X = torch.as_tensor(workspace_points(10, seed=5))
    uv, _ = project(cams, X)
    no_skew = Cameras(
        cams.K * torch.tensor([[1.0, 0, 1], [1, 1, 1], [1, 1, 1]], dtype=F64), cams.dist, cams.R, cams.t
    )
    uv0, _ = project(no_skew, X)
    # Same distorted normalized coords; the skew only shifts u by K[0, 1] * y_d.
    y_d = (uv0[..., 1] - cams.K[:, None, 1, 2]) / cams.K[:, None, 1, 1]
    torch.testing.assert_close(uv[..., 0], uv0[..., 0] + cams.K[:, None, 0, 1] * y_d)
    torch.testing.assert_close(uv[..., 1], uv0[..., 1])


def test_project_broadcasts_points_against_cameras():
    cams = cams_of(random_rig((2, 3), seed=6))
    X = torch.as_tensor(workspace_points(12, seed=7)).reshape(2, 1, 6, 3)
    uv, depth = project(cams, X)
    assert uv.shape == (2, 3, 6, 2)
    uv_one, _ = project(cams[1, 2], X[1, 0])
    torch.testing.assert_close(uv[1, 2], uv_one)


def test_project_float32_close_to_float64():
    rig = random_rig((4,), seed=8)
    X = workspace_points(30, seed=9)
    uv64, _ = project(cams_of(rig), torch.as_tensor(X))
    uv32, _ = project(cams_of(rig, torch.float32), torch.as_tensor(X, dtype=torch.float32))
    assert uv32.dtype == torch.float32
    torch.testing.assert_close(uv32.double(), uv64, atol=2e-3, rtol=0)


def test_points_behind_camera_are_flagged_and_finite(dtype):
    cams = cams_of(random_rig((), seed=11), dtype)
    centre = cams.centres()
    axis = cams.R[2]  # optical axis in the world frame
    side = cams.R[0]
    X = torch.stack(
        [centre + axis, centre - axis, centre - 1e-9 * axis + side, centre, centre - 5 * axis + side]
    )
    X = X.detach().requires_grad_(True)
    uv, depth = project(cams, X)
    assert depth[0] > 0 and torch.all(depth[1:] <= 1e-6)
    assert torch.isfinite(uv).all()
    assert torch.isfinite(uv.double().square().sum())  # a residual of a masked point cannot overflow
    uv.sum().backward()
    assert torch.isfinite(X.grad).all()


def test_distort_undistort_round_trip_and_match_opencv():
    rig = random_rig((3,), seed=12, strong=True)
    cams = cams_of(rig)
    X = workspace_points(50, seed=13)
    uv, _ = project(cams, torch.as_tensor(X))
    und = undistort_pixels(cams, uv)
    for i in range(3):
        ref = cv2.undistortPoints(
            uv[i].numpy()[:, None], rig["K"][i], rig["dist"][i], P=rig["K"][i], criteria=CV_CONVERGED
        )
        np.testing.assert_allclose(und[i].numpy(), ref[:, 0], atol=1e-4, rtol=0)
    # and undistorted pixels are the distortion-free projection
    pinhole = Cameras(cams.K, None, cams.R, cams.t)
    torch.testing.assert_close(und, project(pinhole, torch.as_tensor(X))[0], atol=1e-6, rtol=0)
    xy = torch.rand(3, 20, 2, dtype=F64) - 0.5
    torch.testing.assert_close(undistort(distort(xy, cams.dist), cams.dist), xy, atol=1e-10, rtol=0)


def test_undistort_float32_and_no_distortion():
    rig = random_rig((2,), seed=14)
    cams = cams_of(rig, torch.float32)
    uv = torch.tensor([[[10.0, 20.0], [200.0, 180.0], [350.0, 330.0]]]).expand(2, 3, 2)
    und = undistort_pixels(cams, uv)
    assert und.dtype == torch.float32
    torch.testing.assert_close(und.double(), undistort_pixels(cams.to(F64), uv.double()), atol=1e-3, rtol=0)
    plain = Cameras(cams.K, None, cams.R, cams.t)
    torch.testing.assert_close(undistort_pixels(plain, uv), uv)


def test_distort_shape_errors():
    with pytest.raises(ValueError, match="xy"):
        distort(torch.zeros(3, 3), torch.zeros(5))
    with pytest.raises(ValueError, match="dist"):
        undistort(torch.zeros(4, 2), torch.zeros(4))
    with pytest.raises(ValueError, match="broadcast"):
        distort(torch.zeros(2, 4, 2), torch.zeros(3, 5))


def test_project_shape_errors():
    cams = cams_of(random_rig((3,), seed=15))
    with pytest.raises(ValueError, match="X"):
        project(cams, torch.zeros(3, 4, 2, dtype=F64))
    with pytest.raises(ValueError, match="X"):
        project(cams, torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="broadcast"):
        project(cams, torch.zeros(2, 4, 3, dtype=F64))
    with pytest.raises(ValueError, match="dtype"):
        project(cams, torch.zeros(4, 3))
    with pytest.raises(ValueError, match="uv"):
        pixel_rays(cams, torch.zeros(3, 4, 3, dtype=F64))
    with pytest.raises(ValueError, match="uv"):
        undistort_pixels(cams, torch.zeros(3, 4, dtype=F64))


# ----------------------------------------------------------------------------------------------------------
# Rays
# ----------------------------------------------------------------------------------------------------------


def test_pixel_rays_pass_through_the_projected_point():
    rig = random_rig((2, 3), seed=16, skew=True)
    cams = cams_of(rig)
    X = torch.as_tensor(workspace_points(8, seed=17))
    uv, _ = project(cams, X)
    o, d = pixel_rays(cams, uv)
    assert o.shape == d.shape == (2, 3, 8, 3)
    torch.testing.assert_close(torch.linalg.vector_norm(d, dim=-1), torch.ones(2, 3, 8, dtype=F64))
    torch.testing.assert_close(o, cams.centres()[:, :, None].expand(2, 3, 8, 3))
    # X - o is parallel to d and in front: (X - o) = |X - o| d
    v = X - o
    torch.testing.assert_close(v, torch.linalg.vector_norm(v, dim=-1, keepdim=True) * d, atol=1e-9, rtol=0)


# ----------------------------------------------------------------------------------------------------------
# Rotations
# ----------------------------------------------------------------------------------------------------------


def rotation_cases() -> torch.Tensor:
    axis = torch.nn.functional.normalize(
        torch.tensor([[0.3, -0.5, 0.8], [1.0, 0, 0], [0.0, 0.6, -0.8]], dtype=F64)
    )
    angles = torch.tensor(
        [0.0, 1e-12, 1e-7, 1e-3, 0.3, math.pi / 2, 2.5, math.pi - 1e-3, math.pi - 1e-8, math.pi], dtype=F64
    )
    return (axis[:, None] * angles[None, :, None]).reshape(-1, 3)


def test_rodrigues_matches_opencv_both_ways():
    rvecs = torch.cat([rotation_cases(), torch.randn(20, 3, dtype=F64)])
    R = rodrigues_to_matrix(rvecs)
    for r, Rm in zip(rvecs.numpy(), R.numpy()):
        np.testing.assert_allclose(Rm, cv2.Rodrigues(r)[0], atol=1e-12)
        back = matrix_to_rodrigues(torch.as_tensor(Rm)).numpy()
        # the angle-pi case is ambiguous in sign; compare the rotations there
        np.testing.assert_allclose(cv2.Rodrigues(back)[0], Rm, atol=1e-12)
    r_back = matrix_to_rodrigues(R)
    small = torch.linalg.vector_norm(rvecs, dim=-1) < 3.0
    torch.testing.assert_close(r_back[small], rvecs[small], atol=1e-12, rtol=0)
    assert torch.all(torch.linalg.vector_norm(r_back, dim=-1) <= math.pi + 1e-12)


def test_rodrigues_shapes_and_float32():
    r = torch.randn(2, 5, 3)
    R = rodrigues_to_matrix(r)
    assert R.shape == (2, 5, 3, 3) and R.dtype == torch.float32
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3).expand(2, 5, 3, 3), atol=1e-5, rtol=0)
    assert matrix_to_rodrigues(R).shape == (2, 5, 3)
    with pytest.raises(ValueError, match="rvec"):
        rodrigues_to_matrix(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="R"):
        matrix_to_rodrigues(torch.zeros(3, 4))


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.4, 2.0, math.pi - 1e-3])
def test_rodrigues_gradcheck(angle):
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=F64), dim=0)
    r = (axis * angle).requires_grad_(True)
    assert gradcheck(rodrigues_to_matrix, (r,))
    R = rodrigues_to_matrix(r).detach().requires_grad_(True)
    assert gradcheck(matrix_to_rodrigues, (R,))


# ----------------------------------------------------------------------------------------------------------
# Triangulation
# ----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lead", [(), (5,), (2, 3)])
def test_triangulate_pixels_recovers_noise_free_points(lead):
    rig = random_rig(lead + (4,), seed=20 + len(lead), strong=True)
    cams = cams_of(rig)
    X = torch.as_tensor(workspace_points(7, seed=21))
    uv, depth = project(cams, X)
    assert torch.all(depth > 0)
    X_hat, valid = triangulate_pixels(cams, uv)
    assert X_hat.shape == lead + (7, 3) and valid.shape == lead + (7,)
    assert valid.all()
    torch.testing.assert_close(X_hat, X.expand_as(X_hat), atol=1e-6, rtol=0)


def test_triangulate_pixels_matches_opencv_two_views():
    rig = random_rig((2,), seed=22, strong=True)
    cams = cams_of(rig)
    X = workspace_points(25, seed=23)
    uv, _ = project(cams, torch.as_tensor(X))
    X_hat, valid = triangulate_pixels(cams, uv)
    assert valid.all()
    P = cams.projection_matrices().numpy()
    und = [
        cv2.undistortPoints(
            uv[i].numpy()[:, None], rig["K"][i], rig["dist"][i], P=rig["K"][i], criteria=CV_CONVERGED
        )[:, 0].T
        for i in range(2)
    ]
    Xh = cv2.triangulatePoints(P[0], P[1], und[0], und[1])
    ref = (Xh[:3] / Xh[3]).T
    np.testing.assert_allclose(X_hat.numpy(), ref, atol=1e-6, rtol=0)


def test_triangulate_pixels_weights_broadcast_and_shape_errors():
    cams = cams_of(random_rig((3,), seed=24))
    uv, _ = project(cams, torch.as_tensor(workspace_points(5, seed=25)))
    X1, _ = triangulate_pixels(cams, uv)
    X2, _ = triangulate_pixels(cams, uv, torch.full((3, 1), 0.5, dtype=F64))
    torch.testing.assert_close(X1, X2)
    with pytest.raises(ValueError, match="weights"):
        triangulate_pixels(cams, uv, torch.ones(2, 5, dtype=F64))
    with pytest.raises(ValueError, match="uv"):
        triangulate_pixels(cams, uv[0])
    with pytest.raises(ValueError, match="dtype"):
        triangulate_pixels(cams, uv.float())
    with pytest.raises(ValueError, match="view dim"):
        triangulate_pixels(cams[0], uv[0, None])


def random_rays(
    shape: tuple[int, ...], seed: int, dtype=F64
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays from random origins through random target points (well conditioned)."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(shape + (3,), generator=g, dtype=dtype)
    target = torch.randn(shape[:-1] + (1, 3), generator=g, dtype=dtype) * 0.1
    d = torch.nn.functional.normalize(
        target - o + 0.05 * torch.randn(shape + (3,), generator=g, dtype=dtype), dim=-1
    )
    w = torch.rand(shape, generator=g, dtype=dtype) + 0.1
    return o, d, w


def lstsq_reference(o: torch.Tensor, d: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """argmin_x sum_v w_v |(I - d_v d_v^T)(x - a_v)|^2 by a generic least-squares solver."""
    P = torch.eye(3, dtype=o.dtype) - d[..., :, None] * d[..., None, :]  # (*, V, 3, 3)
    s = w.sqrt()[..., None, None]
    A = (s * P).flatten(-3, -2)  # (*, 3V, 3)
    b = (s * (P @ o[..., None])).flatten(-3, -2)  # (*, 3V, 1)
    return torch.linalg.lstsq(A, b).solution[..., 0]


@pytest.mark.parametrize("shape", [(3, 4), (2, 5, 6), (2,)])
def test_triangulate_rays_is_the_weighted_least_squares_minimizer(shape):
    o, d, w = random_rays(shape, seed=30)
    X, valid = triangulate_rays(o, d, w)
    assert X.shape == shape[:-1] + (3,) and valid.shape == shape[:-1] and valid.all()
    torch.testing.assert_close(X, lstsq_reference(o, d, w), atol=1e-10, rtol=0)


def test_triangulate_rays_ignores_a_wild_ray_with_zero_weight():
    o, d, w = random_rays((10, 4), seed=31)
    wild_d = torch.nn.functional.normalize(torch.randn(10, 3, dtype=F64), dim=-1)
    o2 = torch.cat([o, 100 * torch.randn(10, 1, 3, dtype=F64)], dim=1)
    d2 = torch.cat([d, wild_d[:, None]], dim=1)
    w2 = torch.cat([w, torch.zeros(10, 1, dtype=F64)], dim=1)
    X, valid = triangulate_rays(o, d, w)
    X2, valid2 = triangulate_rays(o2, d2, w2)
    assert valid2.all()
    torch.testing.assert_close(X2, X, atol=1e-10, rtol=0)
    # with weight, the wild ray does pull the point
    X3, _ = triangulate_rays(o2, d2, w2 + 1.0)
    assert (X3 - X).norm(dim=-1).min() > 1e-3


@pytest.mark.parametrize("scale", [1e-3, 0.37, 250.0])
def test_triangulate_rays_invariant_to_weight_scale(scale):
    o, d, w = random_rays((20, 4), seed=32)
    X, valid = triangulate_rays(o, d, w)
    Xs, valid_s = triangulate_rays(o, d, w * scale)
    torch.testing.assert_close(Xs, X, atol=1e-10, rtol=0)
    assert torch.equal(valid, valid_s)


def test_triangulate_rays_weights_in_both_sums():
    # The paper prints the left-hand sum without weights; that variant is not the weighted minimizer.
    o, d, w = random_rays((1, 3), seed=33)
    o = o + 5.0  # far from the world origin, where the printed variant is visibly off
    X, _ = triangulate_rays(o, d, w)
    eye = torch.eye(3, dtype=F64)
    P = eye - d[..., :, None] * d[..., None, :]
    printed = torch.linalg.solve(P.sum(-3), (w[..., None, None] * P @ o[..., None]).sum(-3))[..., 0]
    torch.testing.assert_close(X, lstsq_reference(o, d, w), atol=1e-10, rtol=0)
    assert (X - printed).norm() > 1e-3


def test_triangulate_rays_default_unit_weights_and_float32():
    o, d, w = random_rays((50, 4), seed=34)
    X, valid = triangulate_rays(o, d)
    torch.testing.assert_close(X, triangulate_rays(o, d, torch.ones_like(w))[0])
    X32, valid32 = triangulate_rays(o.float(), d.float(), w.float())
    assert X32.dtype == torch.float32 and valid32.all()
    torch.testing.assert_close(X32.double(), triangulate_rays(o, d, w)[0], atol=1e-4, rtol=0)


def degenerate_cases(dtype) -> dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(40)
    o = torch.randn(4, 3, generator=g, dtype=dtype)
    d = torch.nn.functional.normalize(torch.randn(4, 3, generator=g, dtype=dtype), dim=-1)
    one = torch.tensor([1.0, 0, 0, 0], dtype=dtype)
    parallel = d[:1].expand(4, 3).clone()
    nearly = torch.nn.functional.normalize(
        parallel + 1e-4 * torch.randn(4, 3, generator=g, dtype=dtype), dim=-1
    )
    return {
        "parallel": (o, parallel, torch.ones(4, dtype=dtype)),
        "nearly parallel": (o, nearly, torch.ones(4, dtype=dtype)),
        "zero weights": (o, d, torch.zeros(4, dtype=dtype)),
        "one view": (o, d, one),
        "one view of one": (o[:1], d[:1], one[:1]),
        "one dominant view": (o, d, torch.tensor([1.0, 1e-9, 1e-9, 0], dtype=dtype)),
    }


def test_triangulate_rays_degenerate_inputs_are_invalid_finite_and_differentiable(dtype):
    for name, (o, d, w) in degenerate_cases(dtype).items():
        o, d, w = (x.detach().clone().requires_grad_(True) for x in (o, d, w))
        X, valid = triangulate_rays(o, d, w)
        assert not valid, name
        assert torch.isfinite(X).all(), name
        X.square().sum().backward()
        for x in (o, d, w):
            assert torch.isfinite(x.grad).all(), name


def test_triangulate_rays_batch_mixes_valid_and_degenerate():
    cases = degenerate_cases(F64)
    o, d, w = random_rays((1, 4), seed=41)
    O = torch.stack([o[0], cases["parallel"][0], cases["zero weights"][0]])
    D = torch.stack([d[0], cases["parallel"][1], cases["zero weights"][1]])
    W = torch.stack([w[0], cases["parallel"][2], cases["zero weights"][2]])
    X, valid = triangulate_rays(O, D, W)
    assert valid.tolist() == [True, False, False]
    torch.testing.assert_close(X[0], triangulate_rays(o, d, w)[0][0])
    torch.testing.assert_close(X[1:], torch.zeros(2, 3, dtype=F64))


def test_triangulate_rays_shape_errors():
    o, d, w = random_rays((2, 4), seed=42)
    with pytest.raises(ValueError, match="origins"):
        triangulate_rays(o[..., :2], d, w)
    with pytest.raises(ValueError, match="directions"):
        triangulate_rays(o, d[0, 0], w)
    with pytest.raises(ValueError, match="broadcast"):
        triangulate_rays(o, d, w[:, :3])
    with pytest.raises(ValueError, match="weights"):
        triangulate_rays(o, d, w.long())
    with pytest.raises(ValueError, match="dtype"):
        triangulate_rays(o.float(), d, w)
    w32 = w.float()
    torch.testing.assert_close(triangulate_rays(o, d, w32)[0], triangulate_rays(o, d, w32.double())[0])
    with pytest.raises(ValueError, match="no views"):
        triangulate_rays(o[:, :0], d[:, :0], w[:, :0])


# ----------------------------------------------------------------------------------------------------------
# Gradients
# ----------------------------------------------------------------------------------------------------------


def test_project_gradcheck():
    rig = random_rig((2,), seed=50, skew=True, strong=True)
    cams = cams_of(rig)
    X = torch.as_tensor(workspace_points(4, seed=51))
    inputs = tuple(x.detach().clone().requires_grad_(True) for x in (cams.K, cams.dist, cams.R, cams.t, X))

    def f(K, dist, R, t, X):
        uv, depth = project(Cameras(K, dist, R, t), X)
        return uv, depth

    assert gradcheck(f, inputs)


def test_undistort_and_pixel_rays_gradcheck():
    rig = random_rig((2,), seed=52, strong=True)
    cams = cams_of(rig)
    uv, _ = project(cams, torch.as_tensor(workspace_points(3, seed=53)))
    inputs = tuple(x.detach().clone().requires_grad_(True) for x in (cams.K, cams.dist, cams.R, cams.t, uv))

    def f(K, dist, R, t, uv):
        c = Cameras(K, dist, R, t)
        return (undistort_pixels(c, uv), *pixel_rays(c, uv))

    assert gradcheck(f, inputs)


@pytest.mark.parametrize("layout", ["interleaved", "planar"])
def test_triangulate_rays_gradcheck(layout, monkeypatch):
    # Small batches use the interleaved solve, large ones the planar one; check the gradients of both.
    import s3k.geometry.triangulation as geometry

    if layout == "planar":
        monkeypatch.setattr(geometry, "_PLANAR_MIN", 0)
    o, d, w = random_rays((3, 4), seed=54)
    w[0, 1] = 0.0
    inputs = tuple(x.detach().clone().requires_grad_(True) for x in (o, d, w))
    assert gradcheck(lambda o, d, w: triangulate_rays(o, d, w)[0], inputs)


def test_triangulate_rays_small_and_planar_paths_agree(monkeypatch):
    import s3k.geometry.triangulation as geometry

    o, d, w = random_rays((40, 5), seed=55)
    w[:3] = 0.0
    X, valid = triangulate_rays(o, d, w)
    monkeypatch.setattr(geometry, "_PLANAR_MIN", 0)
    X2, valid2 = triangulate_rays(o, d, w)
    assert torch.equal(valid, valid2) and valid.sum() == 37
    torch.testing.assert_close(X2, X, atol=1e-10, rtol=0)


def test_triangulate_rays_large_batch_chunks_agree(monkeypatch):
    # Large batches take the de-interleaving product and the cache-sized chunk loop; same answers.
    import s3k.geometry.triangulation as geometry

    monkeypatch.setattr(geometry, "_TRIANGULATE_CHUNK", 5000)
    o, d, w = random_rays((12000, 4), seed=60)
    w[:7] = 0.0
    with torch.no_grad():
        X, valid = triangulate_rays(o, d, w)
    assert not valid[:7].any() and valid[7:].all()
    torch.testing.assert_close(X[7:], lstsq_reference(o[7:], d[7:], w[7:]), atol=1e-9, rtol=0)
    torch.testing.assert_close(X[:7], torch.zeros(7, 3, dtype=F64))
    X32, valid32 = triangulate_rays(o.float(), d.float(), w.float())
    assert torch.equal(valid32, valid)
    torch.testing.assert_close(X32.double(), X, atol=1e-4, rtol=0)


@pytest.mark.slow
def test_triangulate_rays_fused_matches_eager():
    o, d, w = random_rays((300, 4), seed=61)
    w[:5] = 0.0
    for dtype in (torch.float32, F64):
        args = (o.to(dtype), d.to(dtype), w.to(dtype))
        X, valid = triangulate_rays(*args)
        Xf, valid_f = triangulate_rays(*args, fused=True)
        assert torch.equal(valid, valid_f)
        torch.testing.assert_close(Xf, X, atol=1e-4 if dtype == torch.float32 else 1e-10, rtol=0)


def test_closed_form_inverse_of_intrinsics_matches_lapack():
    """The rays' K^-1 in closed form: LAPACK's inverse to rounding, for pinhole K, skewed and cropped ones
    (K' = M K) and general 3x3 matrices, batched."""
    from s3k.geometry.projection import _inverse_3x3

    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[500.0, 0.0, 319.5], [0.0, 480.0, 239.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    M = torch.tensor([[0.4, 0.01, -30.0], [0.0, 0.45, 12.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    general = torch.randn(2, 3, 3, 3, generator=g, dtype=torch.float64) + 3 * eye
    for A in (K, M @ K, general):
        torch.testing.assert_close(_inverse_3x3(A), torch.linalg.inv(A), rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(A @ _inverse_3x3(A), torch.eye(3, dtype=torch.float64).expand_as(A),
                                   rtol=0, atol=1e-12)
