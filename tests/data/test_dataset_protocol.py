"""Both dataset classes, a dataset folder and the crops cut in memory, offer every member of the one dataset
protocol (``s3k.data.protocol.DatasetLike``) that training, validation and evaluation read."""

from __future__ import annotations

import numpy as np
from helpers.synthetic_rig import make_dataset

from s3k.data import Dataset
from s3k.data.crops import cut_crops
from s3k.data.protocol import DatasetLike


def protocol_members() -> set[str]:
    own = set(vars(DatasetLike)) | set(DatasetLike.__annotations__)
    return {name for name in own if not name.startswith("_")}


def test_a_folder_and_its_crops_are_both_datasets(tmp_path):
    folder = Dataset.open(make_dataset(tmp_path / "ds", size=32, labelled=2, unlabelled=2, test=1))
    centres = {int(f): np.zeros(3) for f in folder.frames()}
    crops = cut_crops(folder, centres, extent=0.3, size=16)
    members = protocol_members()
    assert {"frames", "labels", "calibration", "images", "path", "image_size", "resized"} <= members
    for ds in (folder, crops):
        missing = sorted(name for name in members if not hasattr(ds, name))
        assert missing == [], (type(ds).__name__, missing)
    assert crops.frames().tolist() == folder.frames().tolist() and crops.path == folder.path
