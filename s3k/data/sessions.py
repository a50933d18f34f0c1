"""A dataset's sessions: the recordings it holds (other days, other animals), each with its own videos,
calibration and metadata (``docs/dataset-format.md#sessions``).

``frames.csv``'s optional ``session`` column names each frame's session (absent: every frame is in the one
session :data:`DEFAULT_SESSION`); ``s3k.json``'s optional ``sessions`` object holds each session's metadata
(``frame_rate``, ``subject``, ``source``, ...); with ``"calibration": "per_session"`` each session's rig is
``calibration/<session>.json`` (the format of ``calibration.json``). A frame's place in its recording (its
time) is its ``video_frame`` when frames.csv has that column, else its frame id.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.data.cameras import read_static_calibration
from s3k.data.problems import Problems
from s3k.data.splits import distances_to
from s3k.data.tables import FRAMES_FILE, METADATA_FILE, NAME_RE, Frames, Meta
from s3k.geometry import Cameras

SESSION_COLUMN = "session"
DEFAULT_SESSION = "default"
"""The session of the frames of a dataset whose frames.csv has no ``session`` column."""
SESSION_CALIBRATION_DIR = "calibration"


def session_calibration_file(session: str) -> str:
    """The file of a session's rig in a dataset with ``"calibration": "per_session"``."""
    return f"{SESSION_CALIBRATION_DIR}/{session}.json"


def frame_sessions(frames: Frames, P: Problems) -> np.ndarray:
    """``(N,)`` the session of every frame (text); a name that cannot be a file name is reported."""
    values = frames.columns.get(SESSION_COLUMN)
    if values is None:
        return np.full(len(frames.ids), DEFAULT_SESSION, dtype=object)
    for value in sorted(set(values.tolist())):
        if not NAME_RE.match(str(value)):
            i = int(np.flatnonzero(values == value)[0])
            P.error(FRAMES_FILE, SESSION_COLUMN, f"session name {value!r} must be usable as a file name "
                    "(letters, digits, _ . + -)", line=int(frames.lines[i]), frame=int(frames.ids[i]))
    return values.copy()


def session_names(sessions: np.ndarray) -> list[str]:
    """The sessions in the order of their first frame in frames.csv."""
    _, first = np.unique(sessions.astype(str), return_index=True)
    return [str(sessions[i]) for i in sorted(first.tolist())]


def read_session_metadata(meta: Meta, names: list[str], P: Problems) -> dict[str, dict[str, Any]]:
    """Each session's metadata from ``s3k.json``'s ``sessions`` (empty for a session it does not list); a
    ``frame_rate`` that is not a positive number, a ``subject`` that is not text, or a listed session without
    frames is reported."""
    raw = meta.raw.get("sessions", {})
    if not isinstance(raw, dict) or not all(isinstance(v, dict) for v in raw.values()):
        P.error(METADATA_FILE, "sessions", f"must map each session name to an object, got {raw!r}")
        return {name: {} for name in names}
    for name, entry in raw.items():
        if name not in names:
            P.error(METADATA_FILE, f"sessions.{name}", f"session {name!r} has no frame in {FRAMES_FILE} "
                    f"(its sessions: {names})")
        rate = entry.get("frame_rate")
        number = isinstance(rate, (int, float)) and not isinstance(rate, bool)
        if rate is not None and not (number and rate > 0):
            P.error(METADATA_FILE, f"sessions.{name}.frame_rate", f"must be a positive number, got {rate!r}")
        subject = entry.get("subject")
        if subject is not None and not isinstance(subject, str):
            P.error(METADATA_FILE, f"sessions.{name}.subject", f"must be text, got {subject!r}")
    return {name: dict(raw.get(name, {})) for name in names}


def read_session_calibration(root: Path, meta: Meta, sessions: np.ndarray,
                             P: Problems) -> tuple[Cameras | None, dict[str, Cameras]]:
    """``calibration/<session>.json`` of every session: ``(Cameras (N, C) per frame, {session: Cameras
    (C,)})``, float64 in stored-image pixels; ``(None, {...})`` after reporting a missing or wrong file."""
    rigs: dict[str, Cameras] = {}
    ok = True
    for name in session_names(sessions):
        rig = read_static_calibration(root, meta, P, session_calibration_file(name),
                                      f"file missing (s3k.json says calibration is per_session; session "
                                      f"{name!r} has frames)")
        ok = ok and rig is not None
        if rig is not None:
            rigs[name] = rig
    if not ok:
        return None, rigs
    index = {name: i for i, name in enumerate(rigs)}
    rows = torch.as_tensor([index[str(s)] for s in sessions], dtype=torch.long)
    stacked = [torch.stack([getattr(rig, f) for rig in rigs.values()]) for f in ("K", "dist", "R", "t")]
    return Cameras(*(x[rows] for x in stacked)), rigs


def frame_times(frames: Frames) -> np.ndarray:
    """``(N,)`` int64 each frame's place in its recording: its ``video_frame``, else its frame id."""
    index = frames.columns.get("video_frame")
    if index is None:
        return frames.ids.copy()
    return np.asarray([int(v) if str(v).isdigit() else int(f) for v, f in zip(index, frames.ids)],
                      dtype=np.int64)


def label_distances(times: np.ndarray, sessions: np.ndarray, labelled: np.ndarray) -> np.ndarray:
    """``(N,)`` float: frames from each frame (``times``, ``sessions``) to the nearest labelled frame of its
    own session (``labelled`` a boolean mask over the same frames); inf where its session has none."""
    out = np.full(len(times), np.inf)
    for name in set(sessions.tolist()):
        here = sessions == name
        out[here] = distances_to(times[here], times[here & labelled])
    return out


def distance_summary(distances: np.ndarray) -> dict[str, float | None]:
    """``{"median": ..., "min": ...}`` of finite distances in frames (None when there is none)."""
    finite = distances[np.isfinite(distances)]
    if not len(finite):
        return {"median": None, "min": None}
    return {"median": float(np.median(finite)), "min": float(finite.min())}


def per_session_counts(sessions: np.ndarray, splits: np.ndarray,
                       names: list[str]) -> Mapping[str, dict[str, int]]:
    """Frames per split of every session."""
    return {name: {s: int(((sessions == name) & (splits == s)).sum()) for s in ("labelled", "unlabelled",
                                                                                  "test")}
            for name in names}
