"""A run knows the images it was trained on: the part of each camera's frame (the import's crop boxes) and
their size, with its dataset's identity; ``s3k evaluate`` and ``s3k label --run`` refuse a dataset whose
images show another part of the frames, and ``s3k track`` crops videos as the training images were
(``tests/inference/test_track.py`` for the videos)."""

from __future__ import annotations

import json

import pytest
from helpers.synthetic_rig import CAMERAS, KEYPOINTS, make_dataset
from helpers.tiny_detector import save_run

from s3k import cli
from s3k.base.errors import UserError
from s3k.data import Dataset
from s3k.detector import DetectorMeta, load_network
from s3k.detector.geometry_record import dataset_geometry, run_geometry
from s3k.model import UNetConfig

CROPPED = [16.0, 8.0, 48.0, 40.0]  # a 32x32 box of a 64x48 frame, shown at 32x32


def imported_as(path, boxes, frame=(64, 48)):
    """Mark a dataset as imported from ``frame``-sized videos cropped to ``boxes`` (as s3k import records)."""
    meta = json.loads((path / "s3k.json").read_text())
    meta["source"] = {"importer": "sleap", "crop_boxes": {c: list(boxes) for c in CAMERAS},
                      "source_image_size": {c: list(frame) for c in CAMERAS}}
    (path / "s3k.json").write_text(json.dumps(meta))
    return path


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("geometry")
    cropped = imported_as(make_dataset(root / "cropped", size=32, labelled=4, unlabelled=4, test=2), CROPPED)
    whole = imported_as(make_dataset(root / "whole", size=32, labelled=4, unlabelled=4, test=2),
                        [0.0, 0.0, 64.0, 48.0])
    rescaled = imported_as(make_dataset(root / "rescaled", size=32, labelled=4, unlabelled=4, test=2),
                           [2 * v for v in CROPPED], frame=(128, 96))  # the same part at twice the resolution
    return {"cropped": cropped, "whole": whole, "rescaled": rescaled, "root": root}


def tiny_run(path, trained_on):
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(32, 32), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        geometry=dataset_geometry(Dataset.open(trained_on)))
    return save_run(path, meta, seed=0)


def test_training_records_the_geometry_and_the_dataset(datasets, tmp_path):
    run = tmp_path / "run"
    assert cli.main(["train", str(datasets["cropped"]), "--out", str(run), "--steps", "1", "--channels",
                     "8,8", "--batch-labelled", "2", "--batch-unlabelled", "2", "--val-every", "0",
                     "--no-progress", "--threads", "1"]) == 0
    _, meta = load_network(run)
    assert meta.geometry is not None and meta.geometry == run_geometry(run)
    assert meta.geometry["cameras"]["cam2"] == {"box": CROPPED, "frame_size": [64, 48]}
    assert meta.geometry["image_size"] == [32, 32]
    saved = json.loads((run / "config.json").read_text())
    assert meta.geometry["dataset"]["path"] == str(datasets["cropped"].resolve())
    assert meta.geometry["dataset"]["fingerprint"] == saved["dataset_identity"]["fingerprint"]


def test_evaluate_refuses_a_dataset_of_another_part_of_the_frames(datasets, tmp_path, capsys):
    run = tiny_run(tmp_path / "run", datasets["cropped"])
    assert cli.main(["evaluate", str(run), "--data", str(datasets["cropped"]), "--json"]) == 0
    assert cli.main(["evaluate", str(run), "--data", str(datasets["rescaled"]), "--json"]) == 0  # same part
    capsys.readouterr()
    assert cli.main(["evaluate", str(run), "--data", str(datasets["whole"]), "--json"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert (f"camera cam0's images show 0,0,64,48 of its 64x48 frames but the run {run} was trained on "
            "16,8,48,40 of its 64x48 frames") in err
    assert "--crop cam0=16,8,48,40 cam1=16,8,48,40" in err and "--size 32,32" in err
    assert "--ignore-geometry" in err
    assert cli.main(["evaluate", str(run), "--data", str(datasets["whole"]), "--json",
                     "--ignore-geometry"]) == 0


def test_label_with_a_run_refuses_a_dataset_of_another_part_of_the_frames(datasets, tmp_path):
    pytest.importorskip("fastapi")
    from s3k.label.server import create_app

    run = tiny_run(tmp_path / "run", datasets["cropped"])
    with pytest.raises(UserError, match=r"camera cam0's images show 0,0,64,48 .*--ignore-geometry"):
        create_app(datasets["whole"], run)
    assert create_app(datasets["whole"], run, ignore_geometry=True) is not None
    assert create_app(datasets["cropped"], run) is not None


def test_a_run_without_a_record_is_not_checked(datasets, tmp_path):
    from s3k.detector.geometry_record import check_dataset

    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(32, 32), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict())
    run = save_run(tmp_path / "old", meta, seed=0)
    assert run_geometry(run) is None
    check_dataset(run, datasets["whole"])  # nothing recorded, nothing refused


def test_training_records_the_calibration_in_frame_pixels(datasets, tmp_path):
    """The run records its static rig in the pixels of the cameras' full frames (the import's crop and
    resize undone), so that the calibration given to track and stream compares with it."""
    import numpy as np

    from s3k.detector.geometry_record import frame_calibration
    from s3k.inference.rig_check import run_calibration

    run = tmp_path / "run"
    assert cli.main(["train", str(datasets["cropped"]), "--out", str(run), "--steps", "1", "--channels",
                     "8,8", "--batch-labelled", "2", "--batch-unlabelled", "2", "--val-every", "0",
                     "--no-progress", "--threads", "1"]) == 0
    _, meta = load_network(run)
    recorded = meta.geometry["calibration"]
    assert run_calibration(meta, run) == recorded and recorded["units"] == "m"
    ds = Dataset.open(datasets["cropped"])
    K = ds.rig(np.float64).numpy()["K"][2]
    entry = recorded["cameras"]["cam2"]
    assert entry["frame_size"] == [64, 48]
    np.testing.assert_allclose(entry["K"], K + np.array([[0, 0, 16.0], [0, 0, 8.0], [0, 0, 0]]), atol=1e-9)
    np.testing.assert_allclose(entry["R"], ds.rig(np.float64).numpy()["R"][2], atol=0)
    # the same part of frames of twice the resolution: focal lengths and principal points twice as large
    twice = frame_calibration(Dataset.open(datasets["rescaled"]))["cameras"]["cam2"]
    K2 = Dataset.open(datasets["rescaled"]).rig(np.float64).numpy()["K"][2]
    np.testing.assert_allclose(np.asarray(twice["K"])[:2, :2], 2 * K2[:2, :2], atol=1e-9)
    np.testing.assert_allclose(np.asarray(twice["K"])[:2, 2], 2 * (K2[:2, 2] + 0.5) - 0.5 + [32.0, 16.0],
                               atol=1e-9)
