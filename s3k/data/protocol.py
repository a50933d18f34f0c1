"""What every dataset offers, as a ``typing.Protocol``: :class:`DatasetLike`.

Two classes hold datasets: :class:`s3k.data.Dataset` (a dataset folder) and
:class:`s3k.data.crops.CropDataset` (the refining pass's crops, cut in memory). Training, validation,
evaluation, the run's recorded geometry and the label export read either through the members below, so a
function that takes a dataset is typed ``DatasetLike`` and works with both.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from s3k.geometry import Cameras

__all__ = ["DatasetLike"]


class DatasetLike(Protocol):
    """A dataset: frames of a rig of cameras with 2D labels, per frame or static calibration, and images at
    ``image_size`` (docs/dataset-format.md).

    Attributes:
        path: the dataset folder (for crops, the folder they were cut from).
        keypoints, cameras: names, ``K`` and ``C`` of them.
        units: world unit of the calibration and 3D points.
        image_size: ``(W, H)`` of the images served; ``source_image_size`` of the stored ones;
            ``crop_box`` the box of the stored images they show.
        metadata, source: the folder's ``s3k.json`` and where the dataset came from.
        static_calibration: one calibration for every frame.
        frame_ids: every frame id, in the dataset's order.
    """

    path: Path
    keypoints: list[str]
    cameras: list[str]
    units: str
    image_size: tuple[int, int]
    source_image_size: tuple[int, int]
    crop_box: Any
    metadata: Any
    source: Any
    static_calibration: bool
    frame_ids: np.ndarray

    def frames(self, split: str | Sequence[str] | None = None) -> np.ndarray: ...

    def split_of(self, frame_ids: Any) -> np.ndarray: ...

    def calibration(self, frame_ids: Any, dtype: Any = ...) -> Cameras: ...

    def labels(self, frame_ids: Any, dtype: Any = ...) -> tuple[np.ndarray, np.ndarray]: ...

    def points3d(self, frame_ids: Any) -> tuple[np.ndarray, np.ndarray] | None: ...

    @property
    def has_points3d(self) -> bool: ...

    def images(self, frame_ids: Any) -> np.ndarray: ...

    def cached_images(self, frame_ids: Any) -> tuple[np.ndarray, np.ndarray] | None: ...

    def resized(self, image_size: Sequence[int]) -> DatasetLike: ...
