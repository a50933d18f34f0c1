"""The report of ``s3k validate DATASET``: every problem, then what is there.

Unlike :meth:`s3k.data.Dataset.open`, which stops with the errors of the tables, this collects every problem
(tables, calibration, image files and their pixels, labels that give no training target) and reports each one
naming the file, the field and the line/frame/camera, then a summary: frames per split and labels per keypoint
per camera. The dataset is usable when there is no error (and, with ``strict``, no warning).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from s3k.data.checks import check_dataset
from s3k.data.dataset import Dataset
from s3k.data.import_report import calibration_findings
from s3k.data.problems import Problem
from s3k.data.sync import estimate_frame_offsets
from s3k.data.tables import SPLITS

MAX_OFFSET = 10  # frames searched either way by the frame-offset check


def _problem_lines(problems: list[Problem], limit: int) -> list[str]:
    out = []
    shown: Counter = Counter()
    hidden: Counter = Counter()
    for p in problems:
        key = (p.severity, p.file if "/" not in p.file else p.file.rsplit("/", 1)[0] + "/*", p.field)
        if shown[key] < limit:
            out.append(f"{p.severity.upper():7} {p}")
            shown[key] += 1
        else:
            hidden[key] += 1
    for (severity, file, fld), n in hidden.items():
        out.append(f"{severity.upper():7} {file}: field '{fld}': ... and {n} more like the above")
    return out


def _summary_lines(ds: Dataset) -> list[str]:
    out = []
    s = ds.summary()
    W, H = s["image_size"]
    out.append(
        f"dataset {ds.path}: {s['frames']} frames, {len(ds.cameras)} cameras, {len(ds.keypoints)} keypoints, "
        f"images {W}x{H}, calibration {s['calibration']}, units {s['units']}"
    )
    out.append("frames per split: " + ", ".join(f"{name} {s['splits'][name]}" for name in SPLITS))
    if len(ds.sessions) > 1:
        out.append(f"{len(ds.sessions)} sessions (frames per split; calibration {s['calibration']}):")
        for name, counts in s["sessions"].items():
            info = ds.session_info(name)
            about = ", ".join(f"{k.replace('_', ' ')} {info[k]}" for k in ("frame_rate", "subject")
                              if k in info)
            out.append(f"  {name}: " + ", ".join(f"{split} {counts[split]}" for split in SPLITS)
                       + (f" ({about})" if about else ""))
    width = max(len(k) for k in ds.keypoints)
    cam_width = max(6, *(len(c) for c in ds.cameras))
    out.append(
        "labels (visible, inside the image) per split: "
        + ", ".join(f"{name} {s['labels_per_split'][name]}" for name in SPLITS)
    )
    out.append("labels per keypoint and camera in the labelled split:")
    out.append(" " * (width + 2) + " ".join(f"{c:>{cam_width}}" for c in ds.cameras))
    for k in ds.keypoints:
        out.append(f"  {k:<{width}}" + " ".join(f"{s['labels'][k][c]:>{cam_width}}" for c in ds.cameras))
    n_lab = s["splits"]["labelled"]
    out.append(
        f"labelled frames with a keypoint labelled in >= 2 cameras: {s['triangulable_labelled_frames']} of "
        f"{n_lab}; with a usable label (triangulated in front of a camera, inside its image; usable for "
        f"training): {s['usable_labelled_frames']} of {n_lab}"
    )
    if s["points3d"] is None:
        out.append("ground-truth 3D points: none")
    else:
        out.append(f"ground-truth 3D points: {s['points3d']}")
    return out


def _calibration_check(ds: Dataset, path: str | Path) -> list[tuple[str, str]]:
    """``s3k check-calibration``'s consistency test on the labels of the labelled and test frames, as
    ``(severity, line)`` naming the repair (:func:`s3k.data.import_report.calibration_findings`): a camera
    found inconsistent is an error (training would learn wrong targets there), a note a warning."""

    ids = np.concatenate([np.asarray(ds.frames(s), dtype=np.int64) for s in ("labelled", "test")])
    if not len(ids):
        return []
    uv, mask = ds.labels(ids)
    return calibration_findings(ds.calibration(ids, dtype=np.float64), uv, mask, ds.cameras, ds.image_size,
                                path)


def _time_rows(times: np.ndarray, gap: int) -> np.ndarray:
    """Each frame's row in a time axis whose stretches without frames are cut to ``gap`` frames (lags up to
    ``gap - 1`` pair the same frames as in the recording; a long recording sparsely labelled stays small)."""
    order = np.argsort(times, kind="stable")
    t = times[order].astype(np.int64)
    steps = np.minimum(np.diff(t, prepend=t[0]), gap)
    rows = np.empty_like(t)
    rows[order] = np.cumsum(steps)
    return rows


def frame_offset_lines(ds: Dataset) -> list[tuple[str, str]]:
    """Each camera's frame offset against the first camera from the motion of the labelled and test frames'
    labels (:func:`s3k.data.sync.estimate_frame_offsets`), per session, as ``(severity, line)``: a line per
    camera, and a warning naming ``s3k import --frame-offsets`` for an offset that is not 0."""
    out: list[tuple[str, str]] = []
    sessions = ds.sessions if len(ds.sessions) > 1 else [None]
    for session in sessions:
        ids = ds.frames(["labelled", "test"], session=session)
        if len(ids) < 2:
            continue
        rows = _time_rows(ds.frame_times(ids), 2 * MAX_OFFSET + 1)
        uv, mask = ds.labels(ids, dtype=np.float64)
        dense = np.full((len(ds.cameras), int(rows.max()) + 1, len(ds.keypoints), 2), np.nan)
        dense[:, rows] = np.where(mask[..., None], uv, np.nan).transpose(1, 0, 2, 3)
        cams = ds.calibration(ids[:1], dtype=np.float64)[0]
        est = estimate_frame_offsets(dense, cams, MAX_OFFSET)
        where = f"session {session}: " if session is not None else ""
        first = ds.cameras[0]
        if not est.decided[1:].any():
            out.append(("info", f"{where}frame offsets: the labels cannot tell (too few labelled frames "
                                f"within {MAX_OFFSET} frames of each other, or too little motion)"))
            continue
        out.append(("info", f"{where}frame offsets from the labels' motion (N: the camera's frame i shows "
                            f"{first}'s frame i+N; searched within +-{MAX_OFFSET}):"))
        for c, cam in enumerate(ds.cameras):
            if c == 0:
                out.append(("info", f"  {cam}: 0 (the reference)"))
            elif est.decided[c]:
                out.append(("info", f"  {cam}: {int(est.offsets[c]):+d} (epipolar residual "
                                    f"{est.residual_px[c]:.2f} px)"))
            else:
                other = (f"; the best offset, {int(est.best[c]):+d}, lowers the residual by only "
                         f"{100 * est.gain[c]:.0f}%" if est.best[c] else "")
                out.append(("info", f"  {cam}: 0, not decided (its labels' motion cannot tell{other})"))
        for c, cam in enumerate(ds.cameras):
            if est.offsets[c]:
                n = int(est.offsets[c])
                out.append(("warning", f"{where}camera {cam}: its frame i shows {first}'s frame i{n:+d} "
                                       f"(unsynchronized clocks); import the recording again with "
                                       f"--frame-offsets {cam}={n}"))
    return out


def validate_dataset(
    path: str | Path,
    *,
    check_images: bool = True,
    workers: int | None = None,
    max_per_field: int = 10,
    strict: bool = False,
) -> tuple[bool, list[str]]:
    """Check a dataset folder; whether it is usable, and the report's lines.

    Args:
        path: dataset folder.
        check_images: decode every image (False: only check that the files exist).
        workers: image decoding threads (default: CPUs).
        max_per_field: print at most this many problems per file and field.
        strict: warnings make the dataset fail too.

    Returns:
        ``(usable, lines)``: False when there is an error (``UNUSABLE``) or, with ``strict``, a warning; the
        report, one problem or figure a line, the verdict last.
    """
    problems, dataset = check_dataset(path, check_images=check_images, workers=workers)
    errors = [p for p in problems if p.severity == "error"]
    warnings = [p for p in problems if p.severity == "warning"]
    lines = _problem_lines(problems, max_per_field)
    if dataset is not None:
        lines += _summary_lines(dataset)
        for severity, line in _calibration_check(dataset, path):
            lines.append(f"{severity.upper():7} {line}")
            (errors if severity == "error" else warnings).append(Problem(severity, "calibration", None, line))
        for severity, line in frame_offset_lines(dataset):
            if severity == "info":
                lines.append(line)
            else:
                lines.append(f"{severity.upper():7} {line}")
                warnings.append(Problem(severity, "frames", None, line))
    if errors:
        return False, [*lines, f"UNUSABLE: {len(errors)} error(s), {len(warnings)} warning(s) in {path}"]
    if warnings and strict:
        return False, [*lines, f"FAILED (--strict): {len(warnings)} warning(s) in {path}"]
    return True, [*lines, f"OK: {path} ({len(warnings)} warning(s))"]
