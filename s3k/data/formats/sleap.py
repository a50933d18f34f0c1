"""SLEAP analysis HDF5 files (``sleap-convert --format analysis``): :func:`read_sleap_analysis`,
:func:`sleap_analysis_tracks`. SLEAP projects (``.slp``) are read by :mod:`s3k.data.formats.slp`."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from s3k.base.errors import UserError
from s3k.data.formats.labels2d import LabelTable
from s3k.data.formats.skeleton import analysis_edges, check_edges
from s3k.data.formats.slp import TRACK_HINT, read_slp, slp_track_frames, slp_tracks
from s3k.data.hdf5 import open_hdf5

log = logging.getLogger(__name__)


def _names(values, path: Path | str, field: str) -> list[str]:
    """The UTF-8 names of the dataset ``field``, each given once."""
    try:
        names = [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).reshape(-1)]
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: {field!r} holds a name that is not UTF-8 text "
                        f"({exc.object[:40]!r})") from None
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise UserError(f"{path}: {field!r} names {twice[0]!r} more than once; names must be unique")
    return names


def _analysis_arrays(path: str | Path) -> tuple[list[str], np.ndarray, list[str], np.ndarray, list]:
    """``(node names, tracks (frames, nodes, 2, tracks), track names, occupancy (frames, tracks), skeleton
    edges)`` of an analysis file; a point of an unoccupied frame, or with a NaN coordinate, is NaN."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: SLEAP analysis file not found")
    with open_hdf5(path) as h5:
        for key in ("tracks", "node_names"):
            if key not in h5:
                raise UserError(f"{path}: no {key!r} dataset (is this a SLEAP analysis file?)")
        nodes = _names(h5["node_names"][()], path, "node_names")
        tracks = np.asarray(h5["tracks"][()], dtype=np.float64)
        names = _names(h5["track_names"][()], path, "track_names") if "track_names" in h5 else None
        occupancy = np.asarray(h5["track_occupancy"][()]) if "track_occupancy" in h5 else None
        edges = analysis_edges(h5, path)
    n_nodes = len(nodes)
    if tracks.ndim != 4:
        raise UserError(f"{path}: 'tracks' has shape {tracks.shape}, expected 4 dimensions")
    n_tracks = len(names) if names is not None else None
    transposed = tracks.shape[1] == 2 and tracks.shape[2] == n_nodes
    plain = tracks.shape[2] == 2 and tracks.shape[1] == n_nodes
    if transposed and plain and n_tracks is not None:
        transposed = tracks.shape[0] == n_tracks
    if transposed:
        tracks = tracks.transpose(3, 2, 1, 0)  # -> (frames, nodes, 2, tracks)
    elif not plain:
        raise UserError(
            f"{path}: 'tracks' has shape {tracks.shape}; with {n_nodes} node_names expected "
            f"(n_tracks, 2, {n_nodes}, n_frames) or (n_frames, {n_nodes}, 2, n_tracks)"
        )
    n_frames, _, _, n_tracks = tracks.shape
    if names is None:
        names = [f"track_{i}" for i in range(n_tracks)]
    if len(names) != n_tracks:
        raise UserError(f"{path}: 'track_names' has {len(names)} names, 'tracks' has {n_tracks} tracks")
    if occupancy is None:
        occupancy = np.ones((n_frames, n_tracks), dtype=np.uint8)
    if occupancy.shape == (n_tracks, n_frames) and occupancy.shape != (n_frames, n_tracks):
        occupancy = occupancy.T
    if occupancy.shape != (n_frames, n_tracks):
        raise UserError(
            f"{path}: 'track_occupancy' has shape {occupancy.shape}, expected ({n_frames}, {n_tracks})"
        )
    tracks = np.where((occupancy == 0)[:, None, None, :], np.nan, tracks)
    tracks = np.where(np.isnan(tracks).any(axis=2, keepdims=True), np.nan, tracks)
    return nodes, tracks, names, occupancy, edges


def read_sleap_analysis(path: str | Path, track: str | int | None = None) -> LabelTable:
    """Read a SLEAP analysis HDF5 file (``sleap-convert --format analysis``).

    SLEAP writes MATLAB-ordered arrays: ``tracks (n_tracks, 2, n_nodes, n_frames)``, ``track_occupancy
    (n_frames, n_tracks)``, ``node_names (n_nodes,)``, ``track_names (n_tracks,)``. Files written without the
    transposition (``tracks (n_frames, n_nodes, 2, n_tracks)``) are recognized too. Missing points are NaN;
    frames where the track is not occupied are NaN.

    Args:
        path: the ``.h5`` file.
        track: track name or index; may be omitted when the file holds one track.

    Returns:
        The labels of every video frame (``frame_ids = 0..n_frames-1``).
    """
    nodes, tracks, names, _, edges = _analysis_arrays(path)
    path = Path(path)
    n_frames, _, _, n_tracks = tracks.shape
    if track is None:
        if n_tracks != 1:
            raise UserError(f"{path}: {n_tracks} tracks ({', '.join(names)})", hint=TRACK_HINT)
        ti = 0
    elif isinstance(track, int) or (isinstance(track, str) and track.isdigit() and track not in names):
        ti = int(track)
        if not 0 <= ti < n_tracks:
            raise UserError(f"{path}: track index {ti} out of range (0..{n_tracks - 1})")
    else:
        if track not in names:
            raise UserError(f"{path}: no track {track!r} (tracks: {', '.join(names)})",
                            hint="give a track name or index with --sleap-track")
        ti = names.index(track)
    uv = np.ascontiguousarray(tracks[:, :, :, ti])
    if not np.isfinite(uv).any():
        what = f"track {names[ti]!r} has no labelled point" if n_frames else "the file holds 0 frames"
        raise UserError(f"{path}: no labelled frames ({what})")
    return LabelTable(nodes, np.arange(n_frames, dtype=np.int64), uv, str(path),
                      skeleton=check_edges(edges, nodes, f"{path}: edge_names"), skeleton_source=str(path))



def track_frame_counts(path: str | Path, predictions: bool = False) -> dict[str, int]:
    """``{track: frames with a labelled point}`` of a SLEAP analysis file or project (``.slp``: the instances
    labelled by a person, and predicted ones with ``predictions``)."""
    if Path(path).suffix.lower() == ".slp":
        return slp_track_frames(path, predictions)
    _, tracks, names, _, _ = _analysis_arrays(path)
    counts = np.isfinite(tracks).any(axis=(1, 2)).sum(axis=0)
    return {name: int(n) for name, n in zip(names, counts)}


def default_track(paths: list[str | Path], predictions: bool = False) -> str | None:
    """The track to import when none is named and the SLEAP files hold several: the one labelled in the most
    frames (of all files; the first on a tie), said in a note. None when they hold at most one track."""
    counts: dict[str, int] = {}
    for path in paths:
        for name, n in track_frame_counts(path, predictions).items():
            counts[name] = counts.get(name, 0) + n
    counts = {name: n for name, n in counts.items() if n}
    if len(counts) < 2:
        return None
    chosen = max(counts, key=counts.__getitem__)
    listed = ", ".join(f"{name} {n}" for name, n in counts.items())
    log.info(f"note: {len(counts)} tracks are labelled (frames: {listed}); importing {chosen}, the most "
          "labelled (--sleap-track NAME picks another, --sleap-track all writes one dataset per track)")
    return chosen


def sleap_analysis_tracks(path: str | Path) -> list[str]:
    """Track names of a SLEAP analysis file (``track_<i>`` where it names none)."""
    with open_hdf5(path) as h5:
        if "track_names" in h5:
            return _names(h5["track_names"][()], path, "track_names")
        if "tracks" in h5:
            return [f"track_{i}" for i in range(int(h5["tracks"].shape[0]))]
    raise UserError(f"{path}: no 'tracks' dataset (is this a SLEAP analysis file?)")


def read_sleap_file(path: str | Path, camera: str, track: str | int | None = None,
                    camera_map: Mapping[str, str] | None = None, predictions: bool = False) -> LabelTable:
    """One camera's labels from a SLEAP analysis file (``.h5``) or project (``.slp``, its video of
    ``camera``; :func:`s3k.data.formats.slp.read_slp`)."""
    if Path(path).suffix.lower() == ".slp":
        mine = {camera: camera_map[camera]} if camera_map and camera in camera_map else None
        tables = read_slp(path, [camera], camera_map=mine, track=track, predictions=predictions)
        return tables[camera]
    return read_sleap_analysis(path, track=track)


def sleap_tracks(paths: list[str | Path]) -> list[str]:
    """The track names of SLEAP files (analysis ``.h5`` or project ``.slp``), in first-seen order."""
    names: list[str] = []
    for path in paths:
        found = slp_tracks(path) if Path(path).suffix.lower() == ".slp" else sleap_analysis_tracks(path)
        names += [n for n in found if n not in names]
    if not names:
        raise UserError(f"{', '.join(str(p) for p in paths)}: no tracks; drop --sleap-track all")
    return names
