"""resize_crop: images and intrinsics change together, exactly, in the pixel-centre convention."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from s3k.geometry.warp import crop_resize_matrix, resize_crop, transform_points

W, H = 80, 60
K = np.array([[70.0, 0.0, 39.5], [0.0, 72.0, 29.5], [0.0, 0.0, 1.0]])
POINT = np.array([0.0537, -0.0311, 1.0])  # camera frame (R = I, t = 0)


def project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = K @ X
    return x[:2] / x[2]


def blob_image(uv: np.ndarray, sigma: float = 3.0) -> np.ndarray:
    """A float32 (H, W, 3) image with a Gaussian dot centred at pixel coordinates uv."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    g = 200.0 * np.exp(-((u - uv[0]) ** 2 + (v - uv[1]) ** 2) / (2 * sigma**2))
    return np.repeat(g[..., None], 3, axis=-1).astype(np.float32)


def centroid(image) -> np.ndarray:
    """Intensity-weighted mean pixel (u, v) of channel 0, pixel (0, 0) at the centre of the top-left pixel."""
    img = np.asarray(image, dtype=np.float64)[..., 0]
    v, u = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([(img * u).sum(), (img * v).sum()]) / img.sum()


CASES = {
    "half": (None, (40, 30)),
    "non-integer shrink": (None, (50, 36)),
    "enlarge": (None, (120, 90)),
    "integer crop": ((10, 5, 70, 55), None),
    "crop and shrink": ((10, 5, 70, 55), (30, 25)),
    "fractional crop": ((10.5, 4.25, 70.5, 52.25), (48, 40)),
    "box beyond the image": ((-10, -10, 90, 70), (50, 40)),
}


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("case", list(CASES))
def test_projection_with_new_K_lands_on_the_resized_dot(case: str, backend: str):
    box, out = CASES[case]
    uv = project(K, POINT)
    image = blob_image(uv)
    if backend == "torch":
        new_image, new_K = resize_crop(torch.from_numpy(image), torch.from_numpy(K), box, out)
        assert isinstance(new_image, torch.Tensor) and isinstance(new_K, torch.Tensor)
        new_image, new_K = new_image.numpy(), new_K.numpy()
    else:
        new_image, new_K = resize_crop(image, K, box, out)
    expected_size = out if out is not None else (box[2] - box[0], box[3] - box[1])
    assert new_image.shape == (expected_size[1], expected_size[0], 3)
    np.testing.assert_allclose(centroid(new_image), project(new_K, POINT), atol=0.01)


def test_new_K_is_M_K_with_the_pixel_centre_scale():
    s = 0.5
    _, K2 = resize_crop(np.zeros((H, W, 3), np.uint8), K, None, (40, 30))
    # u -> s (u + 0.5) - 0.5 applied to the principal point; focal lengths scale by s.
    np.testing.assert_allclose(K2[0], [s * K[0, 0], 0.0, s * (K[0, 2] + 0.5) - 0.5], atol=1e-12)
    np.testing.assert_allclose(K2[1], [0.0, s * K[1, 1], s * (K[1, 2] + 0.5) - 0.5], atol=1e-12)
    M = crop_resize_matrix((0, 0, W, H), (40, 30))
    np.testing.assert_array_equal(K2, M @ K)
    # Whole-image box with the same size is the identity.
    np.testing.assert_array_equal(crop_resize_matrix((0, 0, W, H), (W, H)), np.eye(3))


def test_crop_then_resize_composes():
    rng = np.random.default_rng(0)
    for _ in range(20):
        x0, y0 = rng.uniform(-5, 20, 2)
        box1 = (x0, y0, x0 + rng.uniform(30, 60), y0 + rng.uniform(30, 50))
        out1 = tuple(int(s) for s in rng.integers(20, 70, 2))
        a, b = rng.uniform(0, 5, 2)
        box2 = (a, b, a + rng.uniform(8, 15), b + rng.uniform(8, 15))
        out2 = tuple(int(s) for s in rng.integers(10, 40, 2))
        M1, M2 = crop_resize_matrix(box1, out1), crop_resize_matrix(box2, out2)
        # The second box in the first output's edge coordinates, carried back to the original image.
        sx, sy = out1[0] / (box1[2] - box1[0]), out1[1] / (box1[3] - box1[1])
        composed = (
            box1[0] + box2[0] / sx,
            box1[1] + box2[1] / sy,
            box1[0] + box2[2] / sx,
            box1[1] + box2[3] / sy,
        )
        np.testing.assert_allclose(M2 @ M1, crop_resize_matrix(composed, out2), atol=1e-10)


def test_two_step_resize_crop_matches_one_step_on_images():
    uv = project(K, POINT)
    image = blob_image(uv, sigma=4.0)
    step1, K1 = resize_crop(image, K, (8, 4, 72, 52), (32, 24))
    step2, K2 = resize_crop(step1, K1, (4, 2, 28, 22), (48, 40))
    direct, Kd = resize_crop(image, K, (16, 8, 64, 48), (48, 40))
    np.testing.assert_allclose(K2, Kd, atol=1e-12)
    np.testing.assert_allclose(centroid(step2), project(K2, POINT), atol=0.05)
    np.testing.assert_allclose(centroid(direct), project(Kd, POINT), atol=0.05)


def test_integer_crop_is_a_slice_and_keeps_dtype_and_leading_dims():
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(2, 3, H, W, 3), dtype=np.uint8)
    Ks = np.broadcast_to(K, (2, 3, 3, 3))
    out, K2 = resize_crop(images, Ks, (5, 7, 45, 37), None)
    assert out.dtype == np.uint8 and out.shape == (2, 3, 30, 40, 3) and K2.shape == (2, 3, 3, 3)
    np.testing.assert_array_equal(out, images[:, :, 7:37, 5:45])
    np.testing.assert_allclose(K2[..., :2, 2], np.broadcast_to(K[:2, 2] - [5, 7], (2, 3, 2)))
    t_out, t_K = resize_crop(
        torch.from_numpy(images), torch.from_numpy(np.ascontiguousarray(Ks)), (5, 7, 45, 37)
    )
    assert t_out.dtype == torch.uint8
    np.testing.assert_array_equal(t_out.numpy(), out)
    np.testing.assert_allclose(t_K.numpy(), K2)


def test_uint8_shrink_keeps_mean_intensity():
    image = np.full((H, W, 3), 123, np.uint8)
    for backend in (lambda x: x, torch.from_numpy):
        out, _ = resize_crop(backend(image), None, None, (33, 21))
        assert np.asarray(out).dtype == np.uint8
        assert np.abs(np.asarray(out).astype(int) - 123).max() <= 1


def test_numpy_and_torch_agree_when_enlarging():
    image = np.random.default_rng(1).uniform(0, 255, (H, W, 3)).astype(np.float32)
    a, _ = resize_crop(image, None, None, (113, 97))
    b, _ = resize_crop(torch.from_numpy(image), None, None, (113, 97))
    np.testing.assert_allclose(a, b.numpy(), atol=1e-2)


def test_transform_points_matches_K_update():
    M = crop_resize_matrix((3, 1, 50, 41), (20, 17))
    uv = project(K, POINT)
    np.testing.assert_allclose(transform_points(uv, M), project(M @ K, POINT), atol=1e-12)


def test_bad_arguments_raise():
    img = np.zeros((H, W, 3), np.uint8)
    with pytest.raises(ValueError, match="crop_box"):
        resize_crop(img, K, (10, 10, 5, 20), (4, 4))
    with pytest.raises(ValueError, match="crop_box"):
        resize_crop(img, K, (0, 0, 10), (4, 4))
    with pytest.raises(ValueError, match="out_size"):
        resize_crop(img, K, (0.5, 0, 10, 10), None)
    with pytest.raises(ValueError, match="out_size"):
        resize_crop(img, K, None, (0, 4))
    with pytest.raises(ValueError, match="K"):
        resize_crop(img, np.eye(4), None, (4, 4))
    with pytest.raises(ValueError, match="images"):
        resize_crop(np.zeros((4, 4)), K, None, (4, 4))
