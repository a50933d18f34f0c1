"""A calibrated multi-camera recording -> an s3k dataset (the work of ``s3k import``).

The recording is a calibration (anipose ``calibration.toml``, Qualisys ``.qca.txt``, OpenCV / JARVIS YAML or
XML, DeepFly3D pickle: :mod:`s3k.data.formats.calibration_files`), one video or image sequence per camera
(:mod:`s3k.data.video`) and, optionally, 2D labels per camera: SLEAP analysis files
(:mod:`s3k.data.formats.sleap`), DeepLabCut / Lightning Pose CSVs (:mod:`s3k.data.formats.dlc`), OpenPose or
MMPose JSON (:mod:`s3k.data.formats.pose_json`) or a DeepFly3D pose result
(:mod:`s3k.data.formats.deepfly3d`). Frames whose labels have a keypoint in ``min_views`` cameras are split at
random into labelled and test frames; every ``stride``-th other frame is unlabelled (without labels every kept
frame is). Images may be cropped and resized on the way; intrinsics and labels follow exactly (``K' = M K``).
The dataset is written to a temporary folder beside ``out`` and renamed at the end, so a failed import leaves
nothing behind.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from s3k.data.formats.calibration_files import read_calibration
from s3k.data.formats.dlc import find_lightning_pose_csvs, read_dlc_csv
from s3k.data.formats.labels2d import LabelTable, coverage_warnings
from s3k.data.formats.sleap import default_track, read_sleap_file
from s3k.data.import_choices import (
    PADDING_PX,
    Box,
    drop_outside,
    image_areas,
    labelled_count,
    output_size,
    pad_to_one_size,
    split_frames,
)
from s3k.data.rig import Rig
from s3k.errors import UserError
from s3k.outputs import check_replaceable, replace_folder

LABEL_OPTIONS = ("--sleap", "--nwb", "--dlc", "--lightning-pose", "--openpose", "--mmpose", "--deepfly3d")


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def _prepare_rig(calibration: str | Path, videos: Mapping[str, str | Path], units: str | None,
                 regions: Mapping[str, Sequence[float]] | None) -> tuple[Rig, dict[str, tuple[int, int]]]:
    """The calibration's cameras of ``videos`` at the videos' sizes (after ``regions``); the video sizes."""
    from s3k.data import video

    cameras = list(videos)
    rig = read_calibration(calibration, units=units)
    try:
        rig = rig.select(cameras)
    except KeyError as exc:
        raise UserError(f"{calibration}: {exc.args[0]}") from None
    missing = [f"{cam}={p}" for cam, p in videos.items() if not video.exists(p)]
    if missing:
        raise UserError(f"--videos {missing[0]}: no such video file, image folder or image pattern")
    sizes = {cam: video.frame_size(videos[cam]) for cam in cameras}
    rig = rig.with_sizes(sizes)
    if regions:
        unknown = sorted(set(regions) - set(cameras))
        if unknown:
            raise UserError(f"--video-region: cameras {unknown} have no --videos entry "
                            f"({', '.join(cameras)})")
        try:
            rig = rig.with_video_regions({cam: tuple(box) for cam, box in regions.items()})  # type: ignore[misc]
        except ValueError as exc:
            raise UserError(f"--video-region {exc}") from None
    off = [cam for c, cam in enumerate(cameras) if sizes[cam] != tuple(int(v) for v in rig.size[c])]
    if off:
        c = cameras.index(off[0])
        W, H = sizes[off[0]]
        calibrated = {cam: tuple(int(v) for v in rig.size[cameras.index(cam)]) for cam in off}
        padding = all(abs(sizes[cam][i] - calibrated[cam][i]) <= PADDING_PX for cam in off for i in (0, 1))
        regions_hint = " ".join(f"{cam}=0,0,{sizes[cam][0]},{sizes[cam][1]}" for cam in off)
        raise UserError(
            f"{videos[off[0]]}: video is {W}x{H} but {calibration} gives camera {off[0]!r} size "
            f"{rig.size[c][0]}x{rig.size[c][1]}" + (f" ({len(off)} cameras differ)" if len(off) > 1 else ""),
            hint=f"if the videos are the calibrated images with rows or columns cut or added at the bottom "
                 f"and right (an encoder's padding), pass --video-region {regions_hint} (other placements: "
                 "docs/importing.md)" if padding else
                 f"if the video is the calibrated image cropped or padded, declare the region it shows with "
                 f"--video-region {off[0]}=X0,Y0,X1,Y1 (docs/importing.md)",
        )
    return rig, sizes


def _label_tables(
    cameras: list[str], sizes: dict[str, tuple[int, int]], *, sleap, sleap_project, nwb, dlc, lightning_pose,
    openpose, mmpose, deepfly3d, sleap_track, camera_map, accept_predictions, frame_ids_from: str,
    min_score: float, rig: Rig | None = None,
) -> tuple[str, dict[str, str], dict[str, LabelTable]]:
    """``(kind, {camera: file}, {camera: LabelTable})`` of the one label option given (``"none"``, {}, {} for
    none); ``rig``: the cameras at the videos' sizes (a DeepFly3D result's layout is checked against them)."""
    from s3k.data.formats.pose_json import read_mmpose_json, read_openpose_folder

    options = ("--sleap", "--sleap", *LABEL_OPTIONS[1:])
    values = (sleap, sleap_project, nwb, dlc, lightning_pose, openpose, mmpose, deepfly3d)
    given = [(opt, v) for opt, v in zip(options, values) if v]
    if len(given) > 1:
        raise UserError(f"give labels from at most one of {', '.join(LABEL_OPTIONS)} (got "
                        f"{', '.join(opt for opt, _ in given)})")
    if not given:
        return "none", {}, {}
    option = given[0][0]
    if option == "--deepfly3d":
        from s3k.data.formats.deepfly3d import JOINTS, read_deepfly3d_pose

        tables = read_deepfly3d_pose(deepfly3d, sizes, rig)
        if not tables:
            raise UserError(f"--deepfly3d {deepfly3d}: no camera camera_0, camera_1, ... among --videos "
                            f"({', '.join(cameras)})")
        hidden = sorted({len(t.unseen) for t in tables.values()})
        if hidden[-1]:
            shown = hidden[0] if len(hidden) == 1 else f"{hidden[0]} to {hidden[-1]}"
            print(f"note: DeepFly3D's visibility rule leaves {shown} of the {len(JOINTS)} joints unlabelled "
                  "in each camera: those of the fly's far side "
                  "(docs/importing.md#what-happens-to-each-format)")
        return "deepfly3d", {cam: str(deepfly3d) for cam in tables}, tables
    if sleap_project or nwb:
        from s3k.data.formats.nwb import read_nwb
        from s3k.data.formats.slp import read_slp

        if sleap_project:
            if sleap_track is None:
                sleap_track = default_track([sleap_project], accept_predictions)
            tables = read_slp(sleap_project, cameras, camera_map=camera_map, track=sleap_track,
                              predictions=accept_predictions)
        else:
            tables = read_nwb(nwb, cameras, camera_map=camera_map, predictions=accept_predictions)
        source = str(sleap_project or nwb)
        return ("sleap" if sleap_project else "nwb"), {cam: source for cam in tables}, tables
    reader: Callable[[str, str | Path], LabelTable]
    if option == "--sleap":
        files, kind = dict(sleap), "sleap"
        if sleap_track is None:
            sleap_track = default_track(list(files.values()), accept_predictions)
        reader = lambda cam, p: read_sleap_file(p, cam, sleap_track, camera_map, accept_predictions)  # noqa: E731
    elif option == "--openpose":
        files, kind = dict(openpose), "openpose"
        reader = lambda _cam, p: read_openpose_folder(p, min_score)  # noqa: E731
    elif option == "--mmpose":
        files, kind = dict(mmpose), "mmpose"
        reader = lambda _cam, p: read_mmpose_json(p, min_score)  # noqa: E731
    else:
        if dlc:
            files, kind = dict(dlc), "deeplabcut"
        else:
            files = {k: str(v) for k, v in find_lightning_pose_csvs(lightning_pose, cameras).items()}
            kind = "lightning-pose"
        reader = lambda _cam, p: read_dlc_csv(p, frame_ids_from=frame_ids_from)  # noqa: E731
    unknown = sorted(set(files) - set(cameras))
    if unknown:
        raise UserError(f"labels given for cameras {unknown} that have no --videos entry "
                        f"({', '.join(cameras)})")
    tables = {cam: reader(cam, path) for cam, path in files.items()}
    return kind, {cam: str(p) for cam, p in files.items()}, tables


def _skeleton(tables: Mapping[str, LabelTable], labels_keypoints: list[str], keypoints: list[str],
              skeleton: str | Path | None, calibration: str | Path) -> list[tuple[str, str]]:
    """The dataset's skeleton: the file given (``--skeleton``), else the labels' own (SLEAP's edges, a
    DeepLabCut project's config.yaml), else an anipose project's config.toml above the calibration; its edges
    between the kept ``keypoints``."""
    from s3k.data.formats.skeleton import anipose_project_config, check_edges, read_skeleton, unique_edges

    edges: list[tuple[str, str]] = []
    source = ""
    if skeleton is not None:
        edges, source = read_skeleton(skeleton), str(skeleton)
        check_edges(edges, labels_keypoints or keypoints, f"--skeleton {skeleton}")
        if not edges:
            _warn(f"--skeleton {skeleton}: the file gives no skeleton edges")
    else:
        for table in tables.values():
            if table.skeleton:
                edges, source = unique_edges([*edges, *table.skeleton]), source or table.skeleton_source
        config = anipose_project_config(calibration) if not edges else None
        if config is not None:
            edges, source = read_skeleton(config), str(config)
            edges = [e for e in edges if set(e) <= set(labels_keypoints or keypoints)]
    kept = [e for e in edges if set(e) <= set(keypoints)]
    if edges:
        left = len(edges) - len(kept)
        dropped = f" ({left} to keypoints not kept left out)" if left else ""
        print(f"skeleton: {len(kept)} edges from {source}{dropped}")
    return kept


def _frame_counts(videos: Mapping[str, str | Path]) -> dict[str, int]:
    """Frames each video decodes to; a warning when the container header says otherwise."""
    from s3k.data import video

    counts = {}
    for cam, path in videos.items():
        decoded = video.frame_count(path, exact=True)
        header = video.frame_count(path)
        if header != decoded:
            _warn(f"{path}: the header says {header} frames but {decoded} decode; using {decoded}")
        counts[cam] = decoded
    return counts


def _recorded(path: str | Path, out: str | Path) -> str:
    """How ``s3k.json`` records a source file: absolute when given absolute, else relative to the dataset
    folder ``out`` (read back with :func:`s3k.fileio.resolve_from`), so that a dataset moved together with
    its recording keeps finding it."""
    import os

    path = Path(path)
    if path.is_absolute():
        return str(path)
    return Path(os.path.relpath(path.resolve(), Path(out).resolve())).as_posix()


def import_recording(
    calibration: str | Path,
    videos: Mapping[str, str | Path],
    out: str | Path,
    *,
    sleap: Mapping[str, str | Path] | None = None,
    dlc: Mapping[str, str | Path] | None = None,
    lightning_pose: str | Path | None = None,
    openpose: Mapping[str, str | Path] | None = None,
    mmpose: Mapping[str, str | Path] | None = None,
    deepfly3d: str | Path | None = None,
    min_score: float = 0.5,
    sleap_track: str | int | None = None,
    sleap_project: str | Path | None = None,
    nwb: str | Path | None = None,
    camera_map: Mapping[str, str] | None = None,
    accept_predictions: bool = False,
    frame_ids_from: str = "path",
    overwrite: bool = False,
    labelled: int | str | None = None,
    test: int = 0,
    seed: int = 0,
    stride: int = 1,
    min_views: int = 2,
    size: int | tuple[int, int] | None = None,
    scale: float | None = None,
    crops: Mapping[str, Sequence[float]] | None = None,
    units: str | None = None,
    keypoints: Sequence[str] | None = None,
    video_regions: Mapping[str, Sequence[float]] | None = None,
    skeleton: str | Path | None = None,
) -> Path:
    """Convert a recording to a dataset folder; returns the folder.

    Args:
        calibration: a calibration file (or folder) of any format :func:`s3k.data.formats.calibration_files.
            read_calibration` reads.
        videos: ``{camera: video or image sequence}``; the order sets the dataset's camera order.
        out: dataset folder to write (all or nothing: written beside it and renamed at the end).
        sleap: ``{camera: SLEAP analysis .h5 or project .slp}``. Give at most one of ``sleap``,
            ``sleap_project``, ``nwb``, ``dlc``, ``lightning_pose``, ``openpose``, ``mmpose``,
            ``deepfly3d``; with none every frame is unlabelled (``keypoints`` then names the keypoints).
        dlc: ``{camera: DeepLabCut / Lightning Pose label CSV}``.
        lightning_pose: folder with Lightning Pose's multi-view ``CollectedData_<camera>.csv``.
        openpose: ``{camera: folder of OpenPose *_keypoints.json}``.
        mmpose: ``{camera: MMPose / RTMPose predictions .json}``.
        deepfly3d: a DeepFly3D ``df3d_result*.pkl`` (cameras ``camera_0`` ...).
        min_score: detections (OpenPose, MMPose) below this score are unlabelled.
        sleap_track: SLEAP track name or index (default: the most labelled track, when the files have
            several); in a project without tracks,
            the instance index in each frame.
        sleap_project: one SLEAP ``.slp`` project with a video per camera (:mod:`s3k.data.formats.slp`).
        nwb: one NWB file with ndx-pose labels per camera (:mod:`s3k.data.formats.nwb`).
        camera_map: ``{camera: video or camera name in the project / NWB file}`` where names differ.
        accept_predictions: use SLEAP predicted instances / NWB pose estimation series as labels where a
            frame has no labels by a person.
        frame_ids_from: CSV frame index from the image file name's digits (``"path"``) or the row (``"row"``).
        overwrite: replace an existing dataset folder.
        labelled: number of labelled frames, or ``"all"``; None: 10, or all there are after the test frames
            when fewer (the import says so).
        test: number of test frames (their labels are kept for evaluation).
        seed: seed of the random split.
        stride: keep every ``stride``-th video frame as unlabelled.
        min_views: a frame can be labelled/test when a keypoint is labelled in this many cameras.
        size: output image size ``(W, H)``, or the longer side in pixels (aspect kept).
        scale: output image scale factor (instead of ``size``).
        crops: ``{camera: (x0, y0, x1, y1)}`` crop boxes in pixel edge coordinates (default: whole image).
        units: world length unit of the calibration (default: from the file or its board).
        keypoints: keypoints to keep, in this order (default: all, in the label files' order).
        video_regions: ``{camera: (x0, y0, x1, y1)}``: the region of the calibrated image each video shows
            (:meth:`s3k.data.rig.Rig.with_video_regions`), for videos a few pixels smaller or larger.
        skeleton: a file to take the skeleton from (:func:`s3k.data.formats.skeleton.read_skeleton`);
            default: the labels' own (SLEAP, a DeepLabCut project), else an anipose project's config.toml.
    """
    from s3k.data import video
    from s3k.data.writer import DatasetWriter
    from s3k.geometry.warp import crop_resize_matrix, resize_crop, transform_points

    out = Path(out)
    inputs = {"--calibration": calibration, "--videos": list(videos.values())}
    check_replaceable(out, overwrite, inputs)
    if stride < 1:
        raise UserError(f"--stride must be >= 1, got {stride}")
    cameras = list(videos)
    rig, sizes = _prepare_rig(calibration, videos, units, video_regions)

    # Labels per camera.
    kind, files, tables = _label_tables(
        cameras, sizes, sleap=sleap, sleap_project=sleap_project, nwb=nwb, dlc=dlc,
        lightning_pose=lightning_pose, openpose=openpose, mmpose=mmpose, deepfly3d=deepfly3d,
        sleap_track=sleap_track, camera_map=camera_map, accept_predictions=accept_predictions,
        frame_ids_from=frame_ids_from, min_score=min_score, rig=rig)
    names: list[str] = []
    for table in tables.values():
        names += [k for k in table.keypoints if k not in names]
    if not tables:
        if not keypoints:
            raise UserError("no labels given: name the keypoints with --keypoints a,b,c (every frame is "
                            f"imported unlabelled), or give labels with one of {', '.join(LABEL_OPTIONS)}")
        if test:
            raise UserError(f"--test {test}: test frames need labels, and none are given")
    elif keypoints:
        missing = [k for k in keypoints if k not in names]
        if missing:
            raise UserError(f"--keypoints: {missing} not in the labels ({', '.join(names)})")
    label_names = list(names)
    if keypoints:
        names = list(keypoints)
    edges = _skeleton(tables, label_names, names, skeleton, calibration)

    # Frames: the count each video decodes to.
    counts = _frame_counts(videos)
    n_frames = min(counts.values())
    if len(set(counts.values())) > 1:
        _warn(f"videos have different frame counts {counts}; using the first {n_frames} frames")

    # Crop and resize: one pixel map per camera, applied to K and to the labels.
    boxes: list[Box] = [(0.0, 0.0, float(W), float(H)) for W, H in rig.size]
    if not crops and size is None:
        boxes = pad_to_one_size(boxes, cameras)
    for cam, box in (crops or {}).items():
        if cam not in cameras or len(box) != 4:
            raise UserError(f"--crop {cam}={box}: need one of the cameras ({', '.join(cameras)}) and "
                            "x0,y0,x1,y1")
        boxes[cameras.index(cam)] = (float(box[0]), float(box[1]), float(box[2]), float(box[3]))
    out_size = output_size(boxes, size, scale)
    maps = [crop_resize_matrix(box, out_size) for box in boxes]
    arrays = rig.cameras.numpy()
    K_out = np.stack([resize_crop(None, arrays["K"][c], boxes[c], out_size)[1] for c in range(len(cameras))])

    C, Kp = len(cameras), len(names)
    uv = np.full((n_frames, C, Kp, 2), np.nan)
    for c, cam in enumerate(cameras):
        if cam not in tables:
            continue
        table = tables[cam]
        beyond = table.frame_ids >= n_frames
        if beyond.any():
            _warn(f"{table.source}: {int(beyond.sum())} labelled frames beyond the video's {n_frames} frames "
                  "are ignored")
        present = [k for k in names if k in table.keypoints]
        cols = [names.index(k) for k in present]
        dense = table.dense(n_frames, present)
        uv[:, c, cols] = transform_points(dense, maps[c])
    if tables:
        unseen = {cam: table.unseen for cam, table in tables.items()}
        for line in coverage_warnings(np.isfinite(uv).all(-1), cameras, names, files, unseen):
            print(line)
    W, H = out_size
    dropped = drop_outside(uv, image_areas(boxes, rig.size, out_size), cameras, names)
    mask = np.isfinite(uv).all(-1)
    views = mask.sum(axis=1)  # (F, K)
    candidates = np.flatnonzero((views >= min_views).any(axis=1))
    n_labelled = labelled_count(candidates, labelled, test, min_views, dropped) if tables else 0
    splits = split_frames(candidates, np.arange(n_frames), n_labelled, test, seed, stride)

    source = {
        "importer": kind,
        "calibration": _recorded(calibration, out),
        "videos": {cam: _recorded(p, out) for cam, p in videos.items()},
        "labels": {cam: _recorded(p, out) for cam, p in files.items()},
        "crop_boxes": {cam: list(b) for cam, b in zip(cameras, boxes)},
        "source_image_size": {cam: [int(v) for v in rig.size[c]] for c, cam in enumerate(cameras)},
        "split_seed": seed,
    }
    if video_regions:
        source["video_regions"] = {cam: [float(v) for v in box] for cam, box in video_regions.items()}
    what = f"{kind} labels" if tables else "no labels"
    wanted = sorted(splits)
    with replace_folder(out, overwrite) as tmp:
        writer = DatasetWriter(
            tmp, names, cameras, out_size, rig.units,
            calibration=(K_out, arrays["dist"], arrays["R"], arrays["t"]), source=source, skeleton=edges,
            description=f"imported from {what} and {Path(calibration).name}",
        )
        streams = [video.iter_frames(videos[cam], wanted) for cam in cameras]
        for frames in zip(*streams):
            f = frames[0][0]
            images = []
            for c, (i, image) in enumerate(frames):
                if i != f:  # pragma: no cover - iter_frames yields the same ids for every camera
                    raise RuntimeError(f"{videos[cameras[c]]}: decoded frame {i}, expected {f}")
                images.append(resize_crop(image, None, boxes[c], out_size)[0])
            split = splits[f]
            frame_labels = (np.nan_to_num(uv[f]), mask[f]) if split != "unlabelled" else None
            writer.add_frame(f, split, np.stack(images), labels=frame_labels, extra={"video_frame": f})
        writer.close()
    n = {s: sum(1 for v in splits.values() if v == s) for s in ("labelled", "test", "unlabelled")}
    n_labels = int(sum(mask[f].sum() for f, s in splits.items() if s != "unlabelled"))
    print(f"wrote {out}: {len(splits)} frames (labelled {n['labelled']}, test {n['test']}, unlabelled "
          f"{n['unlabelled']}), {C} cameras {', '.join(cameras)}, {Kp} keypoints, {W}x{H} px, "
          f"{n_labels} 2D labels, units {rig.units}")
    import torch

    from s3k.data.import_report import calibration_warnings, kept_labels_summary
    from s3k.geometry import Cameras

    for line in kept_labels_summary(mask.sum(axis=(1, 2)), candidates, splits, n_labelled, test, min_views):
        print(line, file=sys.stderr if line.startswith("warning:") else sys.stdout)
    cams = Cameras.from_numpy(K_out, arrays["dist"], arrays["R"], arrays["t"], dtype=torch.float64)
    for line in calibration_warnings(cams, uv[candidates], mask[candidates], cameras, out_size, out):
        _warn(line)
    if rig.units == "unknown":
        _warn(f"{calibration} does not give its world unit; pass --units (e.g. mm) so that 3D errors have "
              "one")
    return out
