import numpy as np
import pytest

from s3k.data import video


def _frames(n, h=32, w=48, seed=0):
    rng = np.random.default_rng(seed)
    # Distinct, smooth-ish frames: a per-frame base colour plus noise, so each frame is recognisable after
    # lossy coding as well.
    return [
        np.clip(rng.integers(0, 60, (h, w, 3)) + np.array([40 * (i % 5), 25 * i % 200, 200 - 20 * i]), 0, 255)
        .astype(np.uint8)
        for i in range(n)
    ]


@pytest.fixture(scope="module")
def lossless_video(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "cam.mkv"
    frames = _frames(9)
    assert video.write_video(path, frames, fps=25, codec="ffv1") == 9
    return path, frames


def test_metadata(lossless_video):
    path, frames = lossless_video
    assert video.frame_count(path) == len(frames)
    assert video.frame_count(path, exact=True) == len(frames)
    assert video.frame_size(path) == (48, 32)
    assert video.frame_rate(path) == pytest.approx(25.0)


def test_iterate_exact(lossless_video):
    path, frames = lossless_video
    got = list(video.iter_frames(path))
    assert [i for i, _ in got] == list(range(len(frames)))
    for (_, image), ref in zip(got, frames):
        assert image.dtype == np.uint8 and image.shape == (32, 48, 3)
        np.testing.assert_array_equal(image, ref)
    subset = list(video.iter_frames(path, [6, 2, 2]))
    assert [i for i, _ in subset] == [2, 6]
    np.testing.assert_array_equal(subset[1][1], frames[6])


def test_read_frame_random_access(lossless_video):
    path, frames = lossless_video
    for i in [0, 8, 3, 5]:
        np.testing.assert_array_equal(video.read_frame(path, i), frames[i])


def test_read_frame_h264_seeks_to_the_right_frame(tmp_path):
    # libx264 with B-frames and a key-frame interval: seeking must land on frame i, not the key frame.
    frames = _frames(40, h=48, w=64, seed=1)
    path = tmp_path / "cam.mp4"
    video.write_video(path, frames, fps=30, codec="libx264")
    for i in [0, 17, 39, 12]:
        image = video.read_frame(path, i).astype(float)
        errors = [np.abs(image - f).mean() for f in frames]
        assert int(np.argmin(errors)) == i


def test_extract_frames(lossless_video, tmp_path):
    import cv2

    path, frames = lossless_video
    written = video.extract_frames(path, tmp_path / "png", [1, 4])
    assert [p.name for p in written] == ["000001.png", "000004.png"]
    np.testing.assert_array_equal(cv2.imread(str(written[1]))[:, :, ::-1], frames[4])


def test_errors(lossless_video, tmp_path):
    path, frames = lossless_video
    with pytest.raises(FileNotFoundError, match="missing.mp4"):
        video.frame_count(tmp_path / "missing.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video at all")
    with pytest.raises(ValueError, match="bad.mp4"):
        video.frame_count(bad)
    with pytest.raises(IndexError, match="9 frames"):
        list(video.iter_frames(path, [3, 9]))
    with pytest.raises(IndexError):
        video.read_frame(path, 20)
    with pytest.raises(IndexError, match="negative"):
        video.read_frame(path, -1)
    with pytest.raises(ValueError, match="frame 1"):
        video.write_video(tmp_path / "x.mkv", [frames[0], frames[0][:16]], codec="ffv1")
