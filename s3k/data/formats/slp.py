"""SLEAP projects (``.slp``), read and written with sleap-io: :func:`read_slp`, :func:`slp_tracks`,
:func:`write_slp`.

A project holds videos, a skeleton, tracks (animal identities) and labelled frames; each frame holds
instances, either labelled by a person (``Instance``) or predicted by a model (``PredictedInstance``). For s3k
one video is one camera. A camera finds its video by, in this order: an explicit ``camera_map`` entry (video
file name, stem or index), a SLEAP recording session's camera of that name, or a video whose file stem is the
camera name. A project with a single video serves a single camera directly.

Which animal: a track name; an index, meaning the track with that index when the project has tracks and
the instance with that index in each frame when it has none; or nothing, when only one animal is labelled.
Per frame, a person's instance wins over a predicted one; predictions count only with ``predictions=True``.
SLEAP's pixel convention (0, 0 = centre of the top-left pixel) is s3k's; points are kept as stored.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path
from s3k.data.formats.labels2d import LabelTable, unique_edges
from s3k.data.hdf5 import open_hdf5

# The hint of both SLEAP readers (projects here, analysis files in s3k.data.formats.sleap) when several tracks
# hold labels.
TRACK_HINT = "choose one with --sleap-track NAME or INDEX (or --sleap-track all for one dataset per track)"


def _sleap_io() -> Any:
    try:
        import sleap_io
    except ImportError as exc:  # pragma: no cover - installed with s3k's "formats" extra
        raise UserError(f"SLEAP projects need sleap-io ({exc})", hint="pip install 's3k[formats]'") from exc
    return sleap_io


def load_slp(path: str | Path) -> Any:
    """The ``sleap_io.Labels`` of a ``.slp`` file (videos are not opened)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(2, "SLEAP project not found", str(path))
    sio = _sleap_io()
    open_hdf5(path, "HDF5 (SLEAP project)").close()  # nothing read from other files
    try:
        return sio.load_slp(str(path), open_videos=False)
    except Exception as exc:  # noqa: BLE001 - sleap-io raises many kinds for a file it cannot read
        raise UserError(f"{path}: not a readable SLEAP project ({type(exc).__name__}: {exc})") from None


def video_name(video: Any) -> str:
    """A video's name for matching: the file stem, or the folder of an image sequence."""
    filename = video.filename
    if isinstance(filename, (list, tuple)):
        return Path(filename[0]).parent.name if filename else ""
    return Path(str(filename).replace("\\", "/")).stem


def _match_videos(labels: Any, path: Path, cameras: Sequence[str],
                  camera_map: Mapping[str, str] | None) -> dict[str, Any]:
    """``{camera: Video}`` for the cameras that have a video in the project."""
    videos = list(labels.videos)
    names = [video_name(v) for v in videos]
    found: dict[str, Any] = {}
    for cam, key in (camera_map or {}).items():
        if cam not in cameras:
            raise UserError(f"--camera-map {cam}={key}: no camera {cam!r} (cameras: {', '.join(cameras)})")
        hits = [v for v, n in zip(videos, names) if key in (n, str(v.filename), Path(str(v.filename)).name)]
        if not hits and key.isdigit() and int(key) < len(videos):
            hits = [videos[int(key)]]
        if len(hits) != 1:
            raise UserError(f"{path}: --camera-map {cam}={key} matches {len(hits)} videos; the project's "
                            f"videos are {', '.join(names)} (give a file name, stem or index)")
        found[cam] = hits[0]
    for session in getattr(labels, "sessions", []) or []:
        for camera in session.camera_group.cameras:
            video = session.get_video(camera)
            if camera.name in cameras and camera.name not in found and video is not None:
                found[camera.name] = video
    for video, name in zip(videos, names):
        if name in cameras and name not in found:
            found[name] = video
    if not found and len(videos) == 1 and len(cameras) == 1:
        found[cameras[0]] = videos[0]
    if not found:
        raise UserError(
            f"{path}: no video matches a camera ({', '.join(cameras)}); the project's videos are "
            f"{', '.join(names) or 'none'}", hint="name them with --camera-map CAMERA=VIDEO",
        )
    return found


def slp_tracks(path: str | Path) -> list[str]:
    """Names of the tracks used by a project's instances, in the project's order."""
    labels = load_slp(path)
    used = {id(inst.track) for lf in labels.labeled_frames for inst in lf.instances if inst.track is not None}
    return [t.name for t in labels.tracks if id(t) in used]


def slp_track_frames(path: str | Path, predictions: bool = False) -> dict[str, int]:
    """``{track: labelled frames}`` of a project's instances labelled by a person (and predicted ones with
    ``predictions``), in the project's track order; a frame of several videos counts once per video."""
    labels = load_slp(path)
    counts = {t.name: 0 for t in labels.tracks}
    for lf in labels.labeled_frames:
        pool = list(lf.user_instances) + (list(lf.predicted_instances) if predictions else [])
        for name in {i.track.name for i in pool if i.track is not None and i.track.name in counts}:
            counts[name] += 1
    return counts


def _track_choice(labels: Any, path: Path, track: str | int | None) -> tuple[Any | None, int | None]:
    """(the chosen Track or None, the instance index or None)."""
    tracks = list(labels.tracks)
    names = [t.name for t in tracks]
    if track is None:
        return None, None
    text = str(track)
    if text in names:
        return tracks[names.index(text)], None
    if text.isdigit():
        i = int(text)
        if not tracks:
            return None, i
        if i >= len(tracks):
            raise UserError(f"{path}: --sleap-track {i}: the project has {len(tracks)} tracks "
                            f"({', '.join(names)}); indices 0..{len(tracks) - 1}")
        return tracks[i], None
    raise UserError(f"{path}: no track {text!r} (tracks: {', '.join(names) or 'none'})",
                    hint="give a track name or index with --sleap-track")


def _candidates(lf: Any, chosen_track: Any, predictions: bool) -> list[Any]:
    """A labelled frame's instances of ``chosen_track`` (any without one): those labelled by a person, else,
    with ``predictions``, the predicted ones, most confident first."""
    users = list(lf.user_instances)
    if chosen_track is not None:
        users = [i for i in users if i.track is chosen_track]
    if users or not predictions:
        return users
    preds = list(lf.predicted_instances)
    if chosen_track is not None:
        preds = [i for i in preds if i.track is chosen_track]
    return sorted(preds, key=lambda i: -float(i.score))


def _refuse_several_tracks(labels: Any, path: Path, predictions: bool) -> None:
    """Refuse a project whose instances belong to several tracks when none was chosen."""
    used: list[str] = []
    for lf in labels.labeled_frames:
        for inst in _candidates(lf, None, predictions):
            if inst.track is not None and inst.track.name not in used:
                used.append(inst.track.name)
    if len(used) > 1:
        raise UserError(f"{path}: instances of {len(used)} tracks ({', '.join(used)})", hint=TRACK_HINT)


def read_slp(
    path: str | Path,
    cameras: Sequence[str],
    *,
    camera_map: Mapping[str, str] | None = None,
    track: str | int | None = None,
    predictions: bool = False,
) -> dict[str, LabelTable]:
    """One animal's 2D keypoints per camera from a SLEAP project.

    Args:
        path: the ``.slp`` file.
        cameras: camera names to look for (a project with one video serves a single camera).
        camera_map: ``{camera: video file name, stem or index}`` where names do not match.
        track: track name or index, or instance index in a project without tracks; None when one
            animal is labelled.
        predictions: use predicted instances where a frame has no instance labelled by a person.

    Returns:
        ``{camera: LabelTable}`` for the cameras with a video; frame ids are video frame indices.

    Raises:
        UserError: no labelled frames, several animals and none chosen (naming the tracks and
            ``--sleap-track``), an unknown track or camera.
    """
    path = Path(path)
    labels = load_slp(path)
    videos = _match_videos(labels, path, cameras, camera_map)
    chosen_track, instance_index = _track_choice(labels, path, track)
    n_user = sum(len(lf.user_instances) for lf in labels.labeled_frames)
    n_pred = sum(len(lf.predicted_instances) for lf in labels.labeled_frames)
    if n_user == 0 and not (predictions and n_pred):
        if n_pred:
            raise UserError(f"{path}: no instance labelled by a person, only {n_pred} predicted",
                            hint="pass --accept-predictions to use predictions as labels")
        raise UserError(f"{path}: no labelled frames (the project has {len(labels.labeled_frames)} frames "
                        f"and {n_user} instances)")

    if chosen_track is None and instance_index is None:
        _refuse_several_tracks(labels, path, predictions)

    skeletons = list(labels.skeletons)
    if len(skeletons) != 1:
        raise UserError(f"{path}: {len(skeletons)} skeletons; s3k reads projects with one skeleton")
    keypoints = list(skeletons[0].node_names)
    by_video: dict[int, dict[int, np.ndarray]] = {id(v): {} for v in videos.values()}
    for lf in labels.labeled_frames:
        if id(lf.video) not in by_video:
            continue
        pool = _candidates(lf, chosen_track, predictions)
        if instance_index is not None:
            pool = pool[instance_index:instance_index + 1]
        elif chosen_track is None and len(pool) > 1:
            raise UserError(f"{path}: video {video_name(lf.video)} frame {lf.frame_idx} has {len(pool)} "
                            "instances and no tracks tell them apart",
                            hint="choose one with --sleap-track INDEX (the instance's place in each frame)")
        if not pool:
            continue
        uv = np.asarray(pool[0].numpy(invisible_as_nan=True), dtype=np.float64)[:, :2]
        uv[np.isnan(uv).any(axis=1)] = np.nan
        frames = by_video[id(lf.video)]
        frames[int(lf.frame_idx)] = uv if int(lf.frame_idx) not in frames else frames[int(lf.frame_idx)]

    tables = {}
    for cam, video in videos.items():
        frames = by_video[id(video)]
        ids = np.array(sorted(frames), dtype=np.int64)
        uv = np.stack([frames[i] for i in ids]) if len(ids) else np.zeros((0, len(keypoints), 2))
        tables[cam] = LabelTable(keypoints, ids, uv, f"{path} ({video_name(video)})",
                                 skeleton=unique_edges(skeletons[0].edge_names), skeleton_source=str(path))
    if not any(np.isfinite(t.uv).any() for t in tables.values()):
        which = f"track {chosen_track.name!r}" if chosen_track is not None else (
            f"instance {instance_index}" if instance_index is not None else "any instance")
        raise UserError(f"{path}: no labelled frames for {which} in the videos of cameras "
                        f"{', '.join(videos)}")
    return tables


def write_slp(
    path: str | Path,
    tables: Mapping[str, LabelTable],
    videos: Mapping[str, Any],
    *,
    skeleton: Sequence[Sequence[str]] = (),
    rig: Mapping[str, Any] | None = None,
) -> Path:
    """Write per-camera labels as one SLEAP project: one video per camera, instances labelled by a person.

    Args:
        path: the ``.slp`` file to write (written beside, then renamed).
        tables: ``{camera: LabelTable}``; frame ids are the videos' frame indices.
        videos: ``{camera: video file, or a list of image files}`` the project refers to (need not exist;
            an image sequence is written as its folder).
        skeleton: edges as keypoint name pairs.
        rig: ``{camera: (K (3, 3), dist (5,), R (3, 3), t (3,), (W, H))}`` to store as a recording session
            (SLEAP's multi-view calibration); the session also ties each video to its camera by name.
    """

    sio = _sleap_io()
    keypoints = next(iter(tables.values())).keypoints
    sk = sio.Skeleton(nodes=list(keypoints), edges=[list(e) for e in skeleton], name="s3k")
    # An image sequence is referred to by its folder: sleap-io cannot read back a list of files unopened.
    vids = {cam: sio.Video(filename=str(Path(videos[cam][0]).parent) if isinstance(videos[cam], list)
                           else str(videos[cam]), open_backend=False) for cam in tables}
    frames = []
    for cam, table in tables.items():
        for f, uv in zip(table.frame_ids, table.uv):
            if np.isfinite(uv).all(-1).any():
                inst = sio.Instance.from_numpy(np.asarray(uv, dtype=np.float64), skeleton=sk)
                frames.append(sio.LabeledFrame(video=vids[cam], frame_idx=int(f), instances=[inst]))
    cams = []
    for cam in tables:
        if rig is not None and cam in rig:
            K, dist, R, t, size = rig[cam]
            camera = sio.Camera(name=cam, matrix=np.asarray(K), dist=np.asarray(dist),
                                rvec=cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel(),
                                tvec=np.asarray(t), size=tuple(int(s) for s in size))
        else:
            camera = sio.Camera(name=cam)
        cams.append(camera)
    session = sio.RecordingSession(camera_group=sio.CameraGroup(cameras=cams))
    for camera, cam in zip(cams, tables):
        session.add_video(vids[cam], camera)
    labels = sio.Labels(labeled_frames=frames, videos=list(vids.values()), skeletons=[sk], sessions=[session])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        sio.save_slp(labels, str(tmp), verbose=False)
    return path
