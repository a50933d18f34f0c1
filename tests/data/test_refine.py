import numpy as np
import pytest
import torch
from helpers.synthetic_rig import make_dataset

from s3k.base.errors import UserError
from s3k.data import Dataset
from s3k.data.crops import object_centres, write_crop_dataset
from s3k.geometry import project, workspace_centre


def test_crop_dataset_keeps_frames_labels_and_geometry(tmp_path):
    src = make_dataset(tmp_path / "full", size=64, labelled=3, unlabelled=2, test=2)
    full = Dataset.open(src)
    X, known = full.points3d(full.frame_ids)
    centres = {int(f): X[i].mean(axis=0) for i, f in enumerate(full.frame_ids)}
    out = write_crop_dataset(src, tmp_path / "crops", centres, extent=0.3, size=32)
    crops = Dataset.open(out)
    assert crops.image_size == (32, 32)
    assert crops.keypoints == full.keypoints and crops.cameras == full.cameras
    for split in ("labelled", "unlabelled", "test"):
        np.testing.assert_array_equal(crops.frames(split), full.frames(split))
    Xc, known_c = crops.points3d(crops.frame_ids)
    np.testing.assert_allclose(Xc, X, atol=1e-6)
    # ground truth projects through the crops' cameras onto the crops' labels, and the centre onto the middle
    ids = crops.frames("labelled")
    cams = crops.calibration(ids, np.float64)
    uv, mask = crops.labels(ids)
    proj, _ = project(cams, torch.as_tensor(Xc[: len(ids)]).double()[:, None])
    assert mask.any()
    np.testing.assert_allclose(proj.numpy()[mask], uv[mask], atol=1e-3)
    mid, _ = project(cams, torch.as_tensor(np.stack([centres[int(f)] for f in ids])).double()[:, None, None])
    np.testing.assert_allclose(mid.numpy()[..., 0, :], 15.5, atol=1e-6)
    assert not (tmp_path / "crops.tmp").exists()


def test_frames_without_an_estimate_are_named_or_use_the_fallback(tmp_path):
    src = make_dataset(tmp_path / "full", size=32, labelled=2, unlabelled=1, test=1)
    full = Dataset.open(src)
    centres = {int(f): np.zeros(3) for f in full.frame_ids[1:]}
    first = int(full.frame_ids[0])
    with pytest.raises(UserError, match=f"frame {first} "):
        write_crop_dataset(src, tmp_path / "crops", centres, extent=0.3, size=16)
    assert not (tmp_path / "crops").exists()
    write_crop_dataset(src, tmp_path / "crops", centres, extent=0.3, size=16, fallback=True)
    # the frame without an estimate is cut around where its cameras look (the detector's rule)
    crops = Dataset.open(tmp_path / "crops")
    cams = crops.calibration([first], dtype=np.float64)
    middle, valid = workspace_centre(full.calibration([first], dtype=np.float64))
    assert bool(valid.all())
    at, _ = project(cams, middle[:, None, None])
    np.testing.assert_allclose(at.numpy()[..., 0, :], 7.5, atol=1e-6)
    with pytest.raises(UserError, match="--overwrite"):
        write_crop_dataset(src, tmp_path / "crops", centres, extent=0.3, size=16)


def test_object_centres_average_the_finite_keypoints():
    nan = float("nan")
    c = object_centres({3: np.array([[0.0, 0, 0], [2, 2, 2], [nan, nan, nan]]), 4: np.full((3, 3), nan)})
    assert list(c) == [3]
    np.testing.assert_allclose(c[3], [1, 1, 1])
