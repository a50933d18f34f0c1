"""``s3k predict``: per-frame 3D keypoints of a dataset, written in the 3D CSV of ``s3k track``.

A run's :class:`s3k.detector.Detector` (one pass or two) reads every frame of the dataset at its own
resolution, with its own cameras: the same read-out as ``s3k evaluate``, ``s3k track`` and ``s3k stream``.
The CSV is anipose's 3D layout (:mod:`s3k.data.tracks_csv`): ``fnum`` is the dataset frame id, ``x, y, z``
are in the dataset's world units and ``error`` is in the dataset's own image pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from s3k.base.choices import Device
from s3k.data import Dataset
from s3k.data.frames import FrameStore
from s3k.data.tracks_csv import check_output, csv_rows, write_csv
from s3k.detector import Detector, detect_store, split_frames
from s3k.inference.session import RigSession

__all__ = ["PredictSummary", "detect_store", "predict_dataset", "split_frames"]


@dataclass
class PredictSummary:
    """What :func:`predict_dataset` wrote."""

    path: Path
    frames: int
    keypoints: list[str]
    warnings: list[str]


def predict_dataset(run: str | Path | RigSession, data: str | Path, out: str | Path, split: str = "test",
                    batch_size: int = 16, device: Device = "auto", overwrite: bool = False) -> PredictSummary:
    """Predict the frames of a dataset split and write the 3D CSV (:mod:`s3k.data.tracks_csv`).

    Args:
        run: run folder of ``s3k train`` (one pass or two), or a detector placed on the dataset
            (:meth:`s3k.inference.session.RigSession.on_dataset`, whose checks ``s3k predict`` runs).
        data: dataset folder.
        out: CSV file to write; never a file of the dataset.
        split: ``labelled``, ``unlabelled``, ``test`` or ``all``.
        batch_size: frames per forward pass.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``... (for a run folder).
        overwrite: replace an existing ``out``.

    Raises:
        UserError: ``out`` is a file of the dataset, or exists without ``overwrite``.
    """
    out = check_output(out, overwrite, dataset=data)
    detector = run.detector if isinstance(run, RigSession) else Detector.load(run, device)
    ds = Dataset.open(data, cache="none")
    warnings = []
    if list(ds.keypoints) != list(detector.keypoints):
        warnings.append(f"dataset keypoints {ds.keypoints} differ from the model's {detector.keypoints}; "
                        "columns use the model's names")
    store = FrameStore(ds, split_frames(ds, split), preload_mb=0)
    n = 0
    with write_csv(out, detector.keypoints) as writer:
        for batch, pred in detect_store(detector, store, batch_size):
            writer.writerows(csv_rows(batch.frame_ids.tolist(), pred))
            n += len(batch.frame_ids)
    return PredictSummary(out, n, list(detector.keypoints), warnings)
