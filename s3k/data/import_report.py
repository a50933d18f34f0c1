"""What ``s3k import`` and ``s3k validate`` say about a dataset beyond its tables: whether the calibration
agrees with the labels, and how many of the recording's labels the import kept.

A broken calibration trains without error (a camera that carries another camera's parameters gives wrong
targets in that camera, quietly), so both commands run the consistency check of ``s3k check-calibration``
(:func:`s3k.geometry.consistency.check_calibration`) on the labels they have and warn, naming the command that
repairs it. And an import keeps only the labels of the frames it puts in the labelled and test splits: the
summary says how many that is, of how many, and which option keeps more.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from s3k.geometry.consistency import check_calibration

__all__ = ["calibration_findings", "calibration_warnings", "kept_labels_summary"]


def calibration_warnings(cams, uv: np.ndarray, mask: np.ndarray, cameras: Sequence[str],
                         image_size: tuple[int, int], dataset: str | Path) -> list[str]:
    """The findings of :func:`s3k.geometry.consistency.check_calibration` on labels ``uv (B, C, K, 2)``,
    ``mask (B, C, K)`` seen by ``cams`` (``Cameras`` ``(C,)`` or ``(B, C)``), as warnings that name the repair
    (``s3k check-calibration DATASET --recalibrate``); empty when the cameras agree or cannot be judged."""
    return [line for _, line in calibration_findings(cams, uv, mask, cameras, image_size, dataset)]


def calibration_findings(cams, uv: np.ndarray, mask: np.ndarray, cameras: Sequence[str],
                         image_size: tuple[int, int], dataset: str | Path) -> list[tuple[str, str]]:
    """:func:`calibration_warnings` with a severity each: ``"error"`` for cameras the check finds
    inconsistent (training would learn wrong targets there), ``"warning"`` for the other notes."""
    uv, mask = np.asarray(uv, dtype=np.float64), np.asarray(mask, dtype=bool)
    if uv.ndim != 4 or not mask.any():
        return []
    with warnings.catch_warnings():  # too few points for a median: the check says so in its own words
        warnings.simplefilter("ignore", RuntimeWarning)
        check = check_calibration(cams, uv, mask, list(cameras), image_size=image_size)
    repair = f"s3k check-calibration {dataset} --recalibrate flagged"
    out = [("warning", f"calibration: {note} (usually a copy error in the calibration file); check it with "
            f"s3k check-calibration {dataset} and recalibrate the copy with --recalibrate CAM")
           for note in check.notes]
    if check.inconsistent:
        why = "; ".join(d for d in check.decisions if d.endswith("INCONSISTENT"))
        out.append(("error", f"calibration: camera(s) {', '.join(check.inconsistent)} disagree with the "
                   f"others' labels ({why}); training would learn wrong targets there: repair with {repair} "
                   "(it recalibrates them from ChArUco frames), or import without them"))
    return out


def kept_labels_summary(labels_per_frame: np.ndarray, candidates: np.ndarray, splits: dict[int, str],
                        labelled: int | str, test: int, min_views: int) -> list[str]:
    """What the split did to the labels of a recording: how many it kept (those of the labelled and test
    frames) of how many, and the options that keep more.

    Args:
        labels_per_frame: ``(F,)`` the 2D labels of every frame of the recording (inside the images).
        candidates: frames with a keypoint labelled in ``min_views`` cameras (those the split chooses from).
        splits: ``{frame: split}`` written.
        labelled, test: the ``--labelled`` and ``--test`` given.
        min_views: the ``--min-views`` given.
    """
    counts = np.asarray(labels_per_frame)
    total = int(counts.sum())
    if total == 0:
        return []
    lab = [f for f, s in splits.items() if s == "labelled"]
    tst = [f for f, s in splits.items() if s == "test"]
    kept = int(sum(counts[f] for f in lab + tst))
    lines = [f"kept {kept} of the recording's {total} 2D labels: those of {len(lab)} labelled frame(s) "
             f"(--labelled {labelled}) and {len(tst)} test frame(s) (--test {test}), chosen among the "
             f"{len(candidates)} frames with a keypoint labelled in >= {min_views} cameras"]
    dropped = total - kept
    if dropped:
        kept_frames = set(lab + tst)
        left = int(sum(1 for f in np.flatnonzero(counts) if int(f) not in kept_frames))
        lines.append(f"the other {dropped} labels, in {left} frame(s), are not written (those frames are "
                     "unlabelled, for the self-supervised term); pass --labelled all, or a larger --labelled "
                     "or --test, to keep them")
    if not tst:
        lines.append("warning: no test frames: 's3k evaluate' has nothing to score; pass --test N (e.g. "
                     f"--test {max(1, len(candidates) // 3)}) to hold out N labelled frames for evaluation")
    return lines
