"""2D poses of OpenPose and MMPose / RTMPose as JSON, one camera at a time -> :class:`LabelTable`.

- OpenPose (``--write_json DIR``): one file per frame, ``<name>_<frame:012d>_keypoints.json``, holding
  ``people: [{"pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...]}, ...]``. The frame index is the last
  number in the file name. Keypoint names are BODY_25's (25 points) or COCO's (18), else ``kp<i>``.
- MMPose / RTMPose: the ``--save-predictions`` file of MMPose's demos (``{"meta_info": ...,
  "instance_info": [{"frame_id": .., "instances": [...]}, ...]}``) or the inferencer's per-video file (a list
  of ``{"frame_id": .., "instances": [...]}``), each instance ``{"keypoints": [[x, y], ...],
  "keypoint_scores": [...]}``. Frame ``i`` is the ``i``-th entry of the list (the demos number frames from 1,
  the inferencer from 0; the order is the same). Names come from ``meta_info.keypoint_id2name``, else COCO's
  17 for 17 points, else ``kp<i>``.

These are detections, not labels: a point counts only when its score is at least ``min_score``. s3k imports
one animal per recording, so each frame keeps its most confident person (highest mean score).

Pixels (:mod:`s3k.data.formats.pixels`): OpenPose's peak finder adds half a pixel to every peak, so that its
coordinates put the top-left pixel's centre at ``(0.5, 0.5)``; they are moved by -0.5 px into s3k's. MMPose
does not state a convention; its coordinates are kept.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from s3k.base.errors import UserError
from s3k.data.formats.labels2d import LabelTable
from s3k.data.formats.pixels import Convention, to_s3k

COCO17 = ["nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
          "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
          "right_knee", "left_ankle", "right_ankle"]
OPENPOSE_COCO18 = ["Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip",
                   "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar"]
OPENPOSE_BODY25 = ["Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
                   "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
                   "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"]
_DIGITS = re.compile(r"(\d+)")


def _names(n: int, known: list[list[str]]) -> list[str]:
    for names in known:
        if len(names) == n:
            return list(names)
    return [f"kp{i}" for i in range(n)]


def _best(points: list[np.ndarray]) -> np.ndarray | None:
    """The person ``(K, 3)`` with the highest mean score, or None."""
    return max(points, key=lambda p: float(np.nanmean(p[:, 2]))) if points else None


def _table(frames: dict[int, np.ndarray], names: list[str], min_score: float, source: str,
           convention: Convention) -> LabelTable:
    ids = np.array(sorted(frames), dtype=np.int64)
    uv = np.full((len(ids), len(names), 2), np.nan)
    for i, f in enumerate(ids):
        p = frames[int(f)]
        ok = (p[:, 2] >= min_score) & np.isfinite(p[:, :2]).all(-1)
        uv[i, ok] = p[ok, :2]
    return LabelTable(names, ids, to_s3k(uv, convention), source)


def _load_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None


def read_openpose_folder(folder: str | Path, min_score: float = 0.5) -> LabelTable:
    """One camera's OpenPose ``*_keypoints.json`` files (see the module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: OpenPose folder not found")
    files = sorted(folder.glob("*.json"))
    if not files:
        raise UserError(f"{folder}: no OpenPose .json files")
    frames: dict[int, np.ndarray] = {}
    n_points = None
    for row, path in enumerate(files):
        data = _load_json(path)
        if not isinstance(data, dict) or not isinstance(data.get("people"), list):
            raise UserError(f"{path}: not an OpenPose file (no 'people' list)")
        runs = _DIGITS.findall(path.stem)
        frame = int(runs[-1]) if runs else row
        people = []
        for person in data["people"]:
            flat = np.asarray(person.get("pose_keypoints_2d", []), dtype=np.float64)
            if flat.size % 3:
                raise UserError(f"{path}: pose_keypoints_2d has {flat.size} numbers, not x, y, score triples")
            if n_points is not None and flat.size // 3 != n_points:
                raise UserError(f"{path}: {flat.size // 3} keypoints, other files have {n_points}")
            n_points = flat.size // 3
            people.append(flat.reshape(-1, 3))
        best = _best(people)
        if best is not None:
            frames[frame] = best
    if n_points is None:
        raise UserError(f"{folder}: no person detected in any file")
    return _table(frames, _names(n_points, [OPENPOSE_BODY25, OPENPOSE_COCO18]), min_score, str(folder),
                  "corner")


def read_mmpose_json(path: str | Path, min_score: float = 0.5) -> LabelTable:
    """One camera's MMPose / RTMPose predictions file (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: MMPose predictions file not found")
    data = _load_json(path)
    meta: dict = {}
    if isinstance(data, dict) and "instance_info" in data:
        meta = data.get("meta_info") or {}
        data = data["instance_info"]
    if not isinstance(data, list) or not all(isinstance(f, dict) and "instances" in f for f in data):
        raise UserError(f"{path}: not MMPose predictions (expected a list of {{frame_id, instances}} "
                        "entries, or a dict with 'instance_info')")
    frames: dict[int, np.ndarray] = {}
    n_points = None
    for i, entry in enumerate(data):
        people = []
        for inst in entry["instances"] or []:
            try:
                kp = np.asarray(inst["keypoints"], dtype=np.float64).reshape(-1, 2)
                score = np.asarray(inst.get("keypoint_scores", np.ones(len(kp))), dtype=np.float64)
                score = score.reshape(-1)
            except (KeyError, TypeError, ValueError):
                raise UserError(f"{path}: frame entry {i}: an instance without numeric 'keypoints'") from None
            if len(score) != len(kp):
                raise UserError(f"{path}: frame entry {i}: {len(kp)} keypoints but {len(score)} scores")
            if n_points is not None and len(kp) != n_points:
                raise UserError(f"{path}: frame entry {i}: {len(kp)} keypoints, earlier frames have "
                                f"{n_points}")
            n_points = len(kp)
            people.append(np.concatenate([kp, score[:, None]], axis=1))
        best = _best(people)
        if best is not None:
            frames[i] = best
    if n_points is None:
        raise UserError(f"{path}: no instance in any frame")
    id2name = meta.get("keypoint_id2name") if isinstance(meta, dict) else None
    if isinstance(id2name, dict) and len(id2name) == n_points:
        names = [str(id2name.get(str(k), id2name.get(k, f"kp{k}"))) for k in range(n_points)]  # type: ignore[call-overload]
    else:
        names = _names(n_points, [COCO17])
    return _table(frames, names, min_score, str(path), "centre")
