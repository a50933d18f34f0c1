"""Starting a two-pass run: the check of a crop extent too large for the images (a two-pass run's recorded
configuration and the folder a failed start leaves: :class:`s3k.run_folder.RunFolder`)."""

from __future__ import annotations

import numpy as np
import torch

from s3k.data.protocol import DatasetLike
from s3k.geometry import triangulate_labels
from s3k.geometry.warp import metric_crop_boxes


def crop_extent_warning(dataset: DatasetLike, extent: float, crop_size: int, coarse_size: int) -> str | None:
    """A warning when crops of side ``extent`` (world units), centred where the labelled keypoints lie, are at
    least as large as the images in most cameras: the refining pass then sees the whole image, at no finer a
    scale than the coarse pass. None otherwise, or when no labelled keypoint can be triangulated."""

    ids = dataset.frames("labelled")
    if not len(ids):
        return None
    uv, mask = dataset.labels(ids)
    cams = dataset.calibration(ids, dtype=np.float64)
    X, valid = triangulate_labels(cams, torch.from_numpy(uv), torch.from_numpy(mask))
    points = X.numpy()[valid.numpy()]
    if not len(points):
        return None
    centre = torch.as_tensor(np.median(points, axis=0))
    boxes, ok = metric_crop_boxes(cams[0], centre, extent)
    sides = (boxes[:, 2] - boxes[:, 0]).numpy()[ok.numpy()]
    W, H = dataset.image_size
    if not len(sides) or float(np.median(sides)) < max(W, H):
        return None
    side = float(np.median(sides))
    return (f"the crops are {extent:g} {dataset.units} wide, about {side:.0f} px in the {W}x{H} images: "
            f"larger than the whole image, so the {crop_size} px crops see the object at "
            f"{crop_size / side:.2f} of its pixels and the coarse pass at {coarse_size / max(W, H):.2f}; "
            "give a smaller side with --crop-extent (world units) or --crop-margin")
