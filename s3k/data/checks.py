"""``check_dataset``: every check of a dataset folder, collecting problems instead of stopping at the first
(the checks of :meth:`s3k.data.dataset.Dataset.open`, every image's pixels, usable labels and label coverage).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from s3k.data.dataset import Dataset, parse_folder
from s3k.data.images import ImageReadError, decode_image, header_size
from s3k.data.problems import DatasetError, Problem, Problems
from s3k.data.sources import PngImages
from s3k.data.tables import FRAMES_FILE, LABELS_FILE
from s3k.data.usable import usable_labels


def check_dataset(
    path: str | Path, check_images: bool = True, workers: int | None = None
) -> tuple[list[Problem], Dataset | None]:
    """Run every check on a dataset folder, collecting problems instead of stopping at the first.

    Besides the checks of :meth:`Dataset.open` (and, with ``check_images``, every image's pixels), a labelled
    frame without a usable label is a warning, and a dataset whose labelled frames give no usable label at
    all is an error (training would have no supervised target; see :func:`s3k.data.usable.usable_labels`).

    Args:
        path: dataset folder.
        check_images: also decode every image and check its size against ``image_size``.
        workers: decoding threads (default: number of CPUs).

    Returns:
        ``(problems, dataset)``: all problems found (errors and warnings) and the dataset when its tables
        could be parsed (None otherwise; a dataset with image errors is still returned for its summary).
    """
    root = Path(path)
    P = Problems()
    contents = parse_folder(root, P)
    if contents is None:
        return P.items, None
    dataset = Dataset(contents, cache="none", workers=workers)
    if contents.calibration_ok:  # else its errors are reported and nothing can be triangulated
        _report_usable_labels(dataset, P)
    _report_label_coverage(dataset, P)
    if check_images and not P.errors:
        _check_all_images(dataset, P)
    elif check_images:
        # Tables have errors; still report unreadable images among the files that exist.
        _check_all_images(dataset, P, only_existing=True)
    return P.items, dataset


def _report_usable_labels(dataset: Dataset, P: Problems) -> None:
    """Warn about each labelled frame without a usable label; an error when no labelled frame has one."""
    ids = dataset.frames("labelled")
    usable = usable_labels(dataset).any(axis=1)
    _, mask = dataset.labels(ids)
    seen_twice = (mask.sum(axis=1) >= 2).any(axis=-1)
    frames = dataset._c.frames
    for frame, twice in zip(ids[~usable].tolist(), seen_twice[~usable].tolist()):
        why = (
            "its keypoints labelled in 2 or more cameras triangulate to no point (near-parallel rays) or to "
            "one that projects outside every image"
            if twice
            else "no keypoint is labelled in 2 or more cameras"
        )
        P.warning(
            FRAMES_FILE, "split", f"labelled frame without a usable label: {why}; the supervised loss has no "
            "target in it", line=int(frames.lines[frames.row_of[frame]]), frame=frame,
        )
    if not len(ids):
        # A recording imported without labels: valid, but training needs labels added first.
        P.warning(
            FRAMES_FILE, "split", "no labelled frames: the dataset can be inspected and labelled, but "
            "training needs labelled frames (add them to frames.csv and labels.csv, or import with labels)",
        )
    elif not usable.any():
        P.error(
            LABELS_FILE, None,
            f"no labelled frame has a usable label ({len(ids)} labelled frames): training needs a keypoint "
            "labelled in 2 or more cameras whose triangulation lies in front of a camera and inside its "
            "image",
        )


def _report_label_coverage(dataset: Dataset, P: Problems) -> None:
    """Warn about a camera or a keypoint without any label in the labelled split, and about keypoints some
    cameras have labels of and others none (keypoint sets that differ between cameras)."""
    ids = dataset.frames("labelled")
    if not len(ids):
        return
    _, mask = dataset.labels(ids)
    counts = mask.sum(axis=0)  # (C, K)
    bare_cams = [c for c in range(len(dataset.cameras)) if not counts[c].any()]
    for c in bare_cams:
        P.warning(LABELS_FILE, "camera", "camera has no label in the labelled frames",
                  camera=dataset.cameras[c])
    for k, name in enumerate(dataset.keypoints):
        if not counts[:, k].any():
            P.warning(LABELS_FILE, "keypoint", "keypoint has no label in the labelled frames", keypoint=name)
    for c, cam in enumerate(dataset.cameras):
        if c in bare_cams:
            continue
        absent = [name for k, name in enumerate(dataset.keypoints) if counts[:, k].any() and not counts[c, k]]
        if absent:
            P.warning(LABELS_FILE, "keypoint", "keypoint sets differ between cameras: this camera has no "
                      f"label of {', '.join(absent)}, which other cameras have", camera=cam)


def _check_all_images(dataset: Dataset, P: Problems, only_existing: bool = False, chunk: int = 64) -> None:
    """Decode every image and report unreadable ones and wrong sizes (for :func:`check_dataset`)."""
    source = dataset._c.source
    W, H = dataset.source_image_size
    if isinstance(source, PngImages):
        jobs = [(int(f), c) for f in dataset.frame_ids for c in range(len(dataset.cameras))]
        if only_existing:
            jobs = [(f, c) for f, c in jobs
                    if (dataset.path / source.relpath(f, dataset.cameras[c])).is_file()]

        def check(job):
            f, c = job
            rel = source.relpath(f, dataset.cameras[c])
            if not (dataset.path / rel).is_file():
                return None  # reported as missing already
            size = header_size(dataset.path / rel)  # a wrong size is reported without decoding
            if size is not None and size != (W, H):
                return dataset._size_problem(f, c, size)
            try:
                image = decode_image(dataset.path / rel, rel)
            except ImageReadError as exc:
                return Problem("error", rel, "image", exc.reason, frame=f, camera=dataset.cameras[c])
            return dataset._size_problem(f, c, (image.shape[1], image.shape[0]))

        with ThreadPoolExecutor(max_workers=dataset._workers) as pool:
            for problem in pool.map(check, jobs):
                if problem is not None:
                    P.items.append(problem)
        return
    # Other sources: decode chunk by chunk, report the first failure of each chunk.
    for start in range(0, len(dataset), chunk):
        rows = np.arange(start, min(start + chunk, len(dataset)))
        buffer = np.empty((len(rows), len(dataset.cameras), H, W, 3), dtype=np.uint8)
        try:
            dataset._decode_into(rows, buffer, resample=False)
        except DatasetError as exc:
            P.items.extend(exc.problems)
