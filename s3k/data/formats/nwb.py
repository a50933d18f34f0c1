"""Neurodata Without Borders files with the ndx-pose extension: 2D labels in and out (:func:`read_nwb`,
:func:`write_nwb_labels`) and 3D tracks out (:func:`write_nwb_tracks`).

ndx-pose keeps human labels as ``PoseTraining`` / ``TrainingFrames``: each ``TrainingFrame`` points to a
source video (an ``ImageSeries``, which may name its camera ``Device``) and a frame index in it, and holds
``SkeletonInstance`` node locations (pixels, with a visibility flag). Model output is ``PoseEstimation``:
one container per camera, one ``PoseEstimationSeries`` (rows = time, columns x, y) per keypoint. s3k reads
both; series are predictions and are used only when asked. A camera is found by, in this order, an explicit
``camera_map`` entry, the camera device's name, the image series' name, or the external video file's stem.
Rows of a ``PoseEstimationSeries`` are taken as the video's frames 0, 1, 2, ...
"""

from __future__ import annotations

import datetime
import uuid
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path
from s3k.data.formats.labels2d import LabelTable, unique_edges
from s3k.data.hdf5 import open_hdf5


def _modules() -> tuple[Any, Any]:
    try:
        import ndx_pose
        import pynwb
    except ImportError as exc:  # pragma: no cover - installed with s3k's "formats" extra
        raise UserError(f"NWB files need pynwb and ndx-pose ({exc})",
                        hint="pip install 's3k[formats]'") from exc
    return pynwb, ndx_pose


def _names(obj: Any) -> list[str]:
    """The names a camera may be known by: device, image series, external file stem."""
    names = []
    device = getattr(obj, "device", None)
    if device is not None:
        names.append(device.name)
    video = obj if obj is not None and obj.__class__.__name__ == "ImageSeries" else None
    if video is None:
        video = getattr(obj, "source_video", None)
        if video is not None and getattr(video, "device", None) is not None:
            names.append(video.device.name)
    if video is not None:
        names.append(video.name)
        files = getattr(video, "external_file", None)
        if files is not None and len(files):
            first = files[0]
            names.append(Path(first.decode() if isinstance(first, bytes) else str(first)).stem)
    if obj is not None and obj.__class__.__name__ == "PoseEstimation":
        names.append(obj.name)
    return names


def _camera_of(obj: Any, cameras: Sequence[str], camera_map: Mapping[str, str]) -> str | None:
    names = _names(obj)
    for cam, key in camera_map.items():
        if key in names:
            return cam
    for name in names:
        if name in cameras and name not in camera_map:
            return name
    return None


def _add_predictions(path: Path, estimations: list[Any], cameras: Sequence[str], camera_map: dict[str, str],
                     tables: dict[str, LabelTable]) -> None:
    """The ``PoseEstimation`` series of the cameras without training frames, as their tables."""
    for pe in estimations:
        found = _camera_of(pe, cameras, camera_map)
        if found is None or found in tables:
            continue
        series = dict(pe.pose_estimation_series)
        names = [str(n) for n in pe.skeleton.nodes[:]] if pe.skeleton is not None else list(series)
        names = [n for n in names if n in series]
        data = [np.asarray(series[n].data[:], dtype=np.float64)[:, :2] for n in names]
        uv = np.stack(data, axis=1)  # (T, K, 2)
        uv[np.isnan(uv).any(axis=2)] = np.nan
        tables[found] = LabelTable(names, np.arange(len(uv), dtype=np.int64), uv, f"{path} ({pe.name})",
                                   skeleton_source=str(path),
                                   skeleton=[e for e in _edges(pe.skeleton, names) if set(e) <= set(names)])


def read_nwb(
    path: str | Path,
    cameras: Sequence[str],
    *,
    camera_map: Mapping[str, str] | None = None,
    predictions: bool = False,
) -> dict[str, LabelTable]:
    """One animal's 2D keypoints per camera from an NWB file (ndx-pose).

    Args:
        path: the ``.nwb`` file.
        cameras: the dataset's camera names.
        camera_map: ``{camera: name in the file}`` (device, image series or video stem) where names differ.
        predictions: read ``PoseEstimation`` series for cameras without training frames.

    Returns:
        ``{camera: LabelTable}`` for the cameras found; frame ids are video frame indices.
    """
    pynwb, ndx_pose = _modules()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(2, "NWB file not found", str(path))
    camera_map = dict(camera_map or {})
    for cam in camera_map:
        if cam not in cameras:
            raise UserError(f"--camera-map {cam}={camera_map[cam]}: no camera {cam!r} "
                            f"(cameras: {', '.join(cameras)})")
    open_hdf5(path, "HDF5 (NWB)").close()  # nothing read from other files
    try:
        io = pynwb.NWBHDF5IO(str(path), "r", load_namespaces=True)
        nwb = io.read()
    except Exception as exc:  # noqa: BLE001 - h5py / hdmf raise many kinds for a file they cannot read
        raise UserError(f"{path}: not a readable NWB file ({type(exc).__name__}: {exc})") from None
    with io:
        objects = list(nwb.objects.values())
        frames: dict[str, dict[int, np.ndarray]] = {}
        keypoints: list[str] | None = None
        edges: list[tuple[str, str]] = []
        seen: list[str] = []
        for obj in objects:
            if not isinstance(obj, ndx_pose.TrainingFrame):
                continue
            instances = list(obj.skeleton_instances.skeleton_instances.values())
            found = _camera_of(obj, cameras, camera_map)
            seen += [n for n in _names(obj)[:1] if n not in seen]
            if found is None or not instances:
                continue
            if len(instances) > 1:
                raise UserError(f"{path}: training frame {obj.name!r} has {len(instances)} skeleton "
                                "instances; s3k imports one animal (write one file per animal)")
            inst = instances[0]
            nodes = [str(n) for n in inst.skeleton.nodes[:]]
            if keypoints is None:
                keypoints, edges = nodes, _edges(inst.skeleton, nodes)
            elif nodes != keypoints:
                raise UserError(f"{path}: training frame {obj.name!r} uses skeleton {nodes}, others "
                                f"{keypoints}")
            uv = np.array(inst.node_locations[:], dtype=np.float64)[:, :2]
            if inst.node_visibility is not None:
                uv[~np.asarray(inst.node_visibility[:], dtype=bool)] = np.nan
            uv[np.isnan(uv).any(axis=1)] = np.nan
            if obj.source_video_frame_index is None:
                raise UserError(f"{path}: training frame {obj.name!r} has no source_video_frame_index")
            frames.setdefault(found, {})[int(obj.source_video_frame_index)] = uv
        tables = {cam: _table(keypoints or [], f, f"{path} ({cam})") for cam, f in frames.items()}
        for table in tables.values():
            table.skeleton, table.skeleton_source = list(edges), str(path)

        estimations = [o for o in objects if isinstance(o, ndx_pose.PoseEstimation)]
        if predictions:
            _add_predictions(path, estimations, cameras, camera_map, tables)
    if not any(np.isfinite(t.uv).any() for t in tables.values()):
        if estimations and not predictions:
            raise UserError(f"{path}: no training frames (labels), only {len(estimations)} PoseEstimation "
                            "containers (predictions)",
                            hint="pass --accept-predictions to use them as labels")
        found = ", ".join(sorted(seen)) if seen else "none"
        raise UserError(f"{path}: no labelled frames for cameras {', '.join(cameras)} (video / camera names "
                        f"in the file: {found})", hint="name them with --camera-map CAMERA=NAME")
    return tables


def _edges(skeleton: Any, nodes: list[str]) -> list[tuple[str, str]]:
    """An ndx-pose skeleton's edges (node index pairs) as keypoint name pairs."""
    if skeleton is None or skeleton.edges is None:
        return []
    all_nodes = [str(n) for n in skeleton.nodes[:]]
    pairs = np.asarray(skeleton.edges[:], dtype=np.int64).reshape(-1, 2)
    return unique_edges((all_nodes[a], all_nodes[b]) for a, b in pairs
                        if 0 <= a < len(all_nodes) and 0 <= b < len(all_nodes))


def _table(keypoints: list[str], frames: dict[int, np.ndarray], source: str) -> LabelTable:
    ids = np.array(sorted(frames), dtype=np.int64)
    uv = np.stack([frames[i] for i in ids]) if len(ids) else np.zeros((0, len(keypoints), 2))
    return LabelTable(list(keypoints), ids, uv, source)


def _new_file(description: str) -> Any:
    pynwb, _ = _modules()
    return pynwb.NWBFile(
        session_description=description,
        identifier=str(uuid.uuid4()),
        session_start_time=datetime.datetime.now(datetime.timezone.utc),
    )


def _cameras(nwb: Any, names: Sequence[str], rig: Mapping[str, Any] | None) -> dict[str, Any]:
    """One device per camera: a ``CalibratedCamera`` (K, R, t, distortion; OpenCV's world -> camera
    convention, as s3k's) where the rig is known."""
    _, ndx_pose = _modules()
    devices = {}
    for cam in names:
        if rig is not None and cam in rig:
            K, dist, R, t = (np.asarray(x, dtype=np.float64) for x in rig[cam][:4])
            device = ndx_pose.CalibratedCamera(
                name=cam, intrinsic_matrix=K, rotation_matrix=R, translation_vector=t,
                distortion_coefficients=dist, description="OpenCV model: x_cam = R x_world + t",
            )
            nwb.add_device(device)
        else:
            device = nwb.create_device(name=cam, description="camera")
        devices[cam] = device
    return devices


def _write(nwb: Any, path: str | Path) -> Path:
    pynwb, _ = _modules()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # the temporary name does not end in .nwb; the file it becomes does
        warnings.filterwarnings("ignore", message=".*does not end in '.nwb'")
        with pynwb.NWBHDF5IO(str(tmp), "w") as io:
            io.write(nwb)
    return path


def write_nwb_labels(
    path: str | Path,
    tables: Mapping[str, LabelTable],
    videos: Mapping[str, Any],
    *,
    skeleton: Sequence[Sequence[str]] = (),
    rig: Mapping[str, Any] | None = None,
    description: str = "2D keypoint labels exported by s3k",
) -> Path:
    """Write per-camera labels as ndx-pose training frames, one per (camera, labelled frame).

    Args:
        path: the ``.nwb`` file (written beside, then renamed).
        tables: ``{camera: LabelTable}``; frame ids are the videos' frame indices.
        videos: ``{camera: video file, or a list of image files}``, stored as external ``ImageSeries``
            named after the camera.
        skeleton: edges as keypoint name pairs.
        rig: ``{camera: (K, dist, R, t, (W, H))}``; cameras become ``CalibratedCamera`` devices.
        description: the file's session description.
    """
    pynwb, ndx_pose = _modules()
    keypoints = list(next(iter(tables.values())).keypoints)
    nwb = _new_file(description)
    devices = _cameras(nwb, list(tables), rig)
    index = {k: i for i, k in enumerate(keypoints)}
    edges = np.array([[index[a], index[b]] for a, b in skeleton], dtype=np.uint8).reshape(-1, 2)
    sk = ndx_pose.Skeleton(name="s3k", nodes=keypoints, edges=edges)
    behavior = nwb.create_processing_module(
        name="behavior", description="keypoint labels in pixels; (0, 0) is the centre of the top-left pixel")
    behavior.add(ndx_pose.Skeletons(skeletons=[sk]))
    series = {}
    n_frames = 1 + max(int(t.frame_ids.max()) for t in tables.values() if len(t.frame_ids))
    for cam in tables:
        files = videos[cam] if isinstance(videos[cam], list) else [str(videos[cam])]
        series[cam] = pynwb.image.ImageSeries(
            name=cam, external_file=files, format="external", starting_frame=list(range(len(files)))
            if len(files) > 1 else [0], rate=1.0, num_samples=max(n_frames, len(files)),
            description=f"video of camera {cam} (an image file per frame, or one video); rate is a "
                        "placeholder, frames are addressed by index",
            device=devices[cam],
        )
    training = []
    for cam, table in tables.items():
        for f, uv in zip(table.frame_ids, table.uv):
            seen = np.isfinite(uv).all(-1)
            if not seen.any():
                continue
            inst = ndx_pose.SkeletonInstance(name="instance", id=np.uint8(0), node_locations=uv,
                                             node_visibility=seen, skeleton=sk)
            training.append(ndx_pose.TrainingFrame(
                name=f"{cam}_frame_{int(f):06d}", annotator="s3k",
                skeleton_instances=ndx_pose.SkeletonInstances(skeleton_instances=[inst]),
                source_video=series[cam], source_video_frame_index=np.uint64(f),
            ))
    behavior.add(ndx_pose.PoseTraining(
        training_frames=ndx_pose.TrainingFrames(training_frames=training),
        source_videos=ndx_pose.SourceVideos(image_series=list(series.values())),
    ))
    return _write(nwb, path)


def write_nwb_tracks(
    path: str | Path,
    keypoints: Sequence[str],
    fnums: np.ndarray,
    X: np.ndarray,
    score: np.ndarray,
    *,
    fps: float,
    units: str,
    rig: Mapping[str, Any] | None = None,
    description: str = "3D keypoints triangulated by s3k",
) -> Path:
    """Write 3D keypoints as an ndx-pose ``MultiCameraPoseEstimation``: one ``PoseEstimationSeries``
    (x, y, z in the calibration's world frame and ``units``; confidence = s3k's score) per keypoint.

    Args:
        path: the ``.nwb`` file.
        keypoints: ``K`` names.
        fnums: ``(T,)`` frame numbers; timestamps are ``fnums / fps`` seconds.
        X: ``(T, K, 3)``, NaN where no point was triangulated.
        score: ``(T, K)`` in [0, 1].
        fps: the videos' frame rate.
        units: world length unit.
        rig: ``{camera: (K, dist, R, t, ...)}`` stored as ``CalibratedCamera`` devices.
    """
    _, ndx_pose = _modules()
    if not fps > 0:
        raise UserError(f"--fps {fps}: must be positive")
    nwb = _new_file(description)
    if rig:
        _cameras(nwb, list(rig), rig)
    sk = ndx_pose.Skeleton(name="s3k", nodes=list(keypoints))
    behavior = nwb.create_processing_module(name="behavior", description="3D keypoints")
    behavior.add(ndx_pose.Skeletons(skeletons=[sk]))
    times = np.asarray(fnums, dtype=np.float64) / float(fps)
    series: list[Any] = []
    for k, kp in enumerate(keypoints):
        series.append(ndx_pose.PoseEstimationSeries(
            name=kp, data=np.asarray(X[:, k], dtype=np.float64), unit=units,
            reference_frame="world frame of the calibration (OpenCV convention: x_cam = R x_world + t)",
            # one timestamps dataset, linked from the other series
            timestamps=series[0] if series else times,
            confidence=np.nan_to_num(np.asarray(score[:, k], dtype=np.float64)),
            confidence_definition="s3k score: mean confidence weight of the keypoint's heatmaps over cameras",
        ))
    behavior.add(ndx_pose.MultiCameraPoseEstimation(
        name="s3k_3d", pose_estimation_series=series, description=description, source_software="s3k",
        skeleton=sk,
    ))
    return _write(nwb, path)


def read_nwb_tracks(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray, str]:
    """``(keypoints, timestamps (T,), X (T, K, 3), confidence (T, K), unit)`` of the first 3D pose
    estimation in an NWB file (what :func:`write_nwb_tracks` writes)."""
    pynwb, ndx_pose = _modules()
    with pynwb.NWBHDF5IO(str(path), "r", load_namespaces=True) as io:
        nwb = io.read()
        for obj in nwb.objects.values():
            if isinstance(obj, (ndx_pose.MultiCameraPoseEstimation, ndx_pose.PoseEstimation)):
                series = dict(obj.pose_estimation_series)
                names = [str(n) for n in obj.skeleton.nodes[:]] if obj.skeleton is not None else list(series)
                first = series[names[0]]
                X = np.stack([np.asarray(series[n].data[:], dtype=np.float64) for n in names], axis=1)
                conf = np.stack([np.asarray(series[n].confidence[:], dtype=np.float64) for n in names],
                                axis=1)
                return names, np.asarray(first.timestamps[:], dtype=np.float64), X, conf, str(first.unit)
    raise UserError(f"{path}: no pose estimation in the file")
