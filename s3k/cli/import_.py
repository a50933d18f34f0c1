"""`s3k import`: a calibrated recording to a dataset (:func:`s3k.data.recording.import_recording`)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.cli import examples
from s3k.cli.options import (
    add_frame_offsets_option,
    camera_pairs,
    frame_offsets,
    name,
    number,
    parse_crops,
    parse_size,
)
from s3k.data import Dataset
from s3k.data import import_labels as fmt
from s3k.data.add_session import import_session, manifest_sessions, merge_session
from s3k.data.formats.sleap import sleap_tracks
from s3k.data.recording import ImageOptions, SplitOptions, import_recording


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Convert a calibrated multi-camera recording to an s3k dataset: a calibration (anipose TOML, "
        "Qualisys .qca.txt, OpenCV/JARVIS YAML or XML, DeepFly3D pickle), one video or image sequence per "
        "camera, and optionally 2D labels (SLEAP analysis files or projects, NWB (ndx-pose), DeepLabCut / "
        "Lightning Pose CSVs, OpenPose or MMPose JSON, a DeepFly3D pose result). Frames with labels are "
        "split into labelled and test frames (test labels are kept for evaluation); the other frames are "
        "unlabelled (their labels, if any, are not written). Without labels every frame is unlabelled. "
        "See docs/importing.md."
    )
    parser.epilog = examples(
        "s3k import --calibration session/calibration.toml --videos back=session/back.mp4 "
        "mid=session/mid.mp4 side=session/side.mp4 --sleap session/labels.slp --test 20 --out data/session",
        "s3k import --calibration calibration.toml --videos cam0=cam0.mp4 cam1=cam1.mp4 "
        "--keypoints nose,tail --stride 10 --out data/unlabelled")
    parser.add_argument("--calibration", default=None,
                        help="anipose calibration.toml, Qualisys .qca.txt, OpenCV/JARVIS .yaml/.xml (a file "
                        "or a folder of one file per camera) or DeepFly3D .pkl; chosen by content")
    parser.add_argument("--videos", nargs="+", default=None, metavar="CAM=FILE",
                        help="one video per camera, or an image sequence (a folder, a glob 'dir/*.png' or a "
                        "pattern 'dir/img_%%05d.jpg'); the order sets the dataset's camera order")
    labels = parser.add_mutually_exclusive_group()
    labels.add_argument("--sleap", nargs="+", metavar="CAM=FILE",
                        help="SLEAP analysis HDF5 (.h5) or project (.slp) per camera, or one FILE.slp "
                             "project with a video per camera (matched by video file stem, SLEAP session "
                             "camera name or --camera-map)")
    labels.add_argument("--nwb", metavar="FILE.nwb",
                        help="NWB file with ndx-pose training frames (or, with --accept-predictions, pose "
                             "estimation series) per camera")
    labels.add_argument("--dlc", nargs="+", metavar="CAM=FILE.csv",
                        help="DeepLabCut / Lightning Pose label CSV per camera")
    labels.add_argument("--lightning-pose", metavar="DIR",
                        help="folder with Lightning Pose's multi-view CSVs CollectedData_<camera>.csv")
    labels.add_argument("--openpose", nargs="+", metavar="CAM=DIR",
                        help="folder of OpenPose *_keypoints.json per camera (detections, see --min-score)")
    labels.add_argument("--mmpose", nargs="+", metavar="CAM=FILE.json",
                        help="MMPose / RTMPose predictions JSON per camera (detections, see --min-score)")
    labels.add_argument("--deepfly3d", metavar="FILE.pkl",
                        help="DeepFly3D df3d_result*.pkl (its points2d, cameras camera_0, camera_1, ...)")
    parser.add_argument("--min-score", type=number(ge=0), default=0.5,
                        help="OpenPose / MMPose points scored below this are unlabelled (default 0.5)")
    parser.add_argument("--sleap-track", default=None,
                        help="SLEAP track name or index when several animals are labelled (default: the "
                             "track labelled in the most frames; in a project without tracks: the instance "
                             "index in each frame); 'all' writes one dataset per track, OUT/<track>")
    parser.add_argument("--camera-map", nargs="+", default=None, metavar="CAM=NAME",
                        help="the video (file name, stem or index) or camera name that holds each camera's "
                             "labels in a SLEAP project or NWB file, where names differ (default: the same "
                             "names)")
    parser.add_argument("--accept-predictions", action="store_true",
                        help="use SLEAP predicted instances / NWB pose estimation series as labels where no "
                             "person labelled the frame")
    parser.add_argument("--frame-ids-from", choices=["path", "row"], default="path",
                        help="CSV frame index from the image file name's digits (default) or the row number")
    parser.add_argument("--out", default=None, help="dataset folder to write")
    parser.add_argument("--into", default=None, metavar="DATASET",
                        help="add the recording to this dataset as a new session (--session): frame ids "
                             "continue after its own, images are resized to its size unless --size or "
                             "--scale says otherwise; cameras and keypoints must be the dataset's "
                             "(docs/importing.md#sessions)")
    parser.add_argument("--dataset", default=None, metavar="DIR",
                        help="with --into and --session: add an s3k dataset of PNG images (e.g. one 's3k "
                             "simulate' wrote) as the new session, instead of a recording")
    parser.add_argument("--session", type=name, default=None,
                        help="the recording's session name (required with --into; with --out the new "
                             "dataset's first session)")
    parser.add_argument("--subject", default=None,
                        help="the animal or object the session recorded, kept in s3k.json's sessions")
    parser.add_argument("--manifest", default=None, metavar="FILE",
                        help="a TOML or JSON file listing sessions, each with its import options "
                             "(docs/importing.md#sessions); with --out they make a new dataset, with --into "
                             "they are added to one")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    parser.add_argument("--labelled", default=None,
                        help="number of labelled frames, or 'all' (default 10, or every frame left after the "
                             "test frames when fewer)")
    parser.add_argument("--test", type=number(int, ge=0), default=0, help="number of test frames (default 0)")
    parser.add_argument("--test-frames", choices=["blocks", "last", "random"], default="blocks",
                        help="how the test frames are chosen: 'blocks' (default) puts them in contiguous "
                             "blocks (--test-blocks) with no labelled frame within --margin frames of them, "
                             "so that evaluation says how a model does on a stretch of recording it has no "
                             "labels of; 'last' holds out the recording's last frames with labels as one "
                             "block (train on its start, test on what follows); 'random' draws them among "
                             "the labelled frames (docs/importing.md#held-out-test-frames)")
    parser.add_argument("--margin", type=number(int, ge=0), default=None,
                        help="frames kept between the test blocks and the nearest labelled frame (default "
                             "10, less on a recording too short for it, said in a note)")
    parser.add_argument("--test-blocks", type=number(int, ge=1), default=1,
                        help="number of contiguous test blocks (default 1)")
    parser.add_argument("--test-sessions", default=None, metavar="A,B",
                        help="sessions held out whole: every frame with labels is a test frame and none of "
                             "their frames trains (with --session or --manifest)")
    parser.add_argument("--seed", type=number(int, ge=0), default=0,
                        help="seed of the random split (default 0)")
    parser.add_argument("--stride", type=number(int, ge=1), default=1,
                        help="keep every STRIDE-th video frame as unlabelled (default 1: all)")
    parser.add_argument("--min-views", type=number(int, ge=1), default=2,
                        help="a frame can be labelled/test when a keypoint is labelled in this many cameras "
                             "(default 2)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--size", default=None,
                      help="output image size: W,H or PX (the longer side, aspect kept; default: the "
                           "videos' size)")
    size.add_argument("--scale", type=number(gt=0, le=16), default=None,
                      help="output image scale factor, e.g. 0.25 (default 1)")
    parser.add_argument("--crop", nargs="+", default=None, metavar="[CAM=]X0,Y0,X1,Y1",
                        help="crop box in pixel edge coordinates, for every camera or one camera (default: "
                        "the whole image)")
    parser.add_argument("--video-region", nargs="+", default=None, metavar="CAM=X0,Y0,X1,Y1",
                        help="the region of the calibrated image a camera's video shows, in pixel edge "
                        "coordinates of the calibrated image: e.g. cam0=0,0,1920,1080 for a 1920x1080 video "
                        "calibrated at 1920x1088 (the intrinsics follow; cameras then a few pixels apart in "
                        "size are padded to the largest; default: the whole calibrated image)")
    add_frame_offsets_option(parser)
    parser.add_argument("--label-pixels", choices=["centre", "corner"], default=None,
                        help="the label files' pixel convention, where it is not their format's: centre "
                        "(0,0 is the centre of the top-left pixel, s3k's and OpenCV's) or corner (0,0 is the "
                        "image's top-left corner) (default: the format's, docs/dataset-format.md#pixels)")
    parser.add_argument("--calibration-pixels", choices=["centre", "corner"], default=None,
                        help="the pixel convention the calibration projects into, where it is not its "
                        "format's (e.g. corner for a calibration fitted to corners found 0.5 px right and "
                        "down of OpenCV's) (default: the format's, centre for every calibration s3k reads)")
    parser.add_argument("--units", type=name, default=None,
                        help="world length unit of the calibration (default: from the file or its board, "
                        "e.g. mm)")
    parser.add_argument("--keypoints", default=None,
                        help="comma-separated keypoints to keep (default all); names them when no labels are "
                        "given")
    parser.add_argument("--skeleton", default=None, metavar="FILE",
                        help="take the skeleton (edges between keypoints, for drawing) from a SLEAP .slp or "
                        "analysis .h5, a DeepLabCut config.yaml, an anipose config.toml or an s3k dataset "
                        "(default: the labels' own: SLEAP's edges, the config.yaml of a DeepLabCut project "
                        "the CSVs lie in, else an anipose config.toml beside or above --calibration)")


LABEL_OPTIONS = {"sleap": "--sleap", "sleap-project": "--sleap", "nwb": "--nwb", "deeplabcut": "--dlc",
                 "lightning-pose": "--lightning-pose", "openpose": "--openpose", "mmpose": "--mmpose",
                 "deepfly3d": "--deepfly3d"}
"""The option that names each label format's files (:data:`s3k.data.import_labels.LABEL_FORMATS`): CAM=FILE
pairs where it takes several values, else one path; ``--sleap`` with one ``FILE.slp`` is a project."""


def _labels(args: argparse.Namespace, track: str | None) -> Any:
    """The label format the options name (:func:`s3k.data.import_labels.build`), or None."""
    options = dict(track=track, accept_predictions=args.accept_predictions,
                   frame_ids_from=args.frame_ids_from, min_score=args.min_score,
                   camera_map=camera_pairs(args.camera_map, "--camera-map") if args.camera_map else None)
    project = _sleap_project(args)
    for kind in fmt.LABEL_FORMATS:
        option = LABEL_OPTIONS[kind]
        given = getattr(args, option[2:].replace("-", "_"))
        if not given or (option == "--sleap" and (kind == "sleap-project") != (project is not None)):
            continue
        files = project if kind == "sleap-project" else (
            camera_pairs(given, option) if isinstance(given, list) else given)
        return fmt.build(kind, files, **options)
    return None


def _sleap_project(args: argparse.Namespace) -> str | None:
    """The one SLEAP project ``--sleap FILE.slp`` names (None for ``CAM=FILE`` pairs)."""
    project = args.sleap[0] if args.sleap and len(args.sleap) == 1 and "=" not in args.sleap[0] else None
    if project is not None and not project.lower().endswith(".slp"):
        raise UserError(f"--sleap {project!r}: expected CAMERA=FILE, or one project FILE.slp")
    return project


def run(args: argparse.Namespace) -> int:
    if args.manifest:
        return import_manifest(args)
    if (args.out is None) == (args.into is None):
        raise UserError("give the dataset to write with --out, or the dataset to add a session to with "
                        "--into")
    if args.into is not None and args.session is None:
        raise UserError(f"--into {args.into}: name the new session with --session NAME")
    held_out = _test_sessions(args.test_sessions)
    if held_out and held_out != [args.session]:
        raise UserError(f"--test-sessions {args.test_sessions}: this import's session is {args.session!r}",
                        hint="name it alone, or list every session in a --manifest")
    if args.dataset is not None:
        return _add_dataset(args, bool(held_out))
    for option, value in (("--calibration", args.calibration), ("--videos", args.videos)):
        if value is None:
            raise UserError(f"{option} is required (or give --dataset or --manifest)")
    videos = dict(camera_pairs(args.videos, "--videos"))
    common: dict[str, Any] = dict(
        split=SplitOptions(
            labelled=args.labelled if args.labelled in (None, "all") else _count(args.labelled, "--labelled"),
            test=args.test, seed=args.seed, stride=args.stride, min_views=args.min_views,
            test_frames="session" if held_out else args.test_frames, margin=args.margin,
            blocks=args.test_blocks),
        images=ImageOptions(
            size=parse_size(args.size), scale=args.scale,
            crops=parse_crops(args.crop, list(videos)) if args.crop else None,
            video_regions=parse_crops(args.video_region, list(videos), "--video-region", every=False)
            if args.video_region else None),
        units=args.units, overwrite=args.overwrite,
        keypoints=[k.strip() for k in args.keypoints.split(",") if k.strip()] if args.keypoints else None,
        skeleton=args.skeleton, frame_offsets=frame_offsets(args.frame_offsets, list(videos)),
        label_pixels=args.label_pixels, calibration_pixels=args.calibration_pixels,
    )
    if args.into is not None:
        if args.sleap_track == "all":
            raise UserError("--sleap-track all writes one dataset per track; give one track with --into")
        del common["overwrite"]
        import_session(args.into, args.session, args.calibration, videos, _labels(args, args.sleap_track),
                       subject=args.subject, **common)
        return 0
    common.update(session=args.session, subject=args.subject)
    if args.sleap_track != "all":
        import_recording(args.calibration, videos, args.out, _labels(args, args.sleap_track), **common)
        return 0

    project = _sleap_project(args)
    files: list[str | Path] = ([project] if project else
                               list(camera_pairs(args.sleap, "--sleap").values()) if args.sleap else [])
    if not files:
        raise UserError("--sleap-track all needs SLEAP labels (--sleap)")
    tracks = sleap_tracks(files)
    for i, track in enumerate(tracks):
        folder = track if re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]*", track) else f"track_{i}"
        print(f"track {track} -> {Path(args.out) / folder}")
        import_recording(args.calibration, videos, Path(args.out) / folder, _labels(args, track), **common)
    return 0


def _add_dataset(args: argparse.Namespace, held_out: bool) -> int:
    """``--into DATASET --session NAME --dataset DIR``: the dataset DIR added as a session."""
    if args.into is None:
        raise UserError(f"--dataset {args.dataset}: give the dataset to add it to with --into")
    if args.calibration or args.videos:
        raise UserError(f"--dataset {args.dataset} brings its own calibration and images: give no "
                        "--calibration or --videos")
    part = Dataset.open(args.dataset, cache="none")
    info = {**part.session_info(part.sessions[0]), "source": part.source or str(args.dataset)}
    if args.subject is not None:
        info["subject"] = args.subject
    merge_session(args.into, args.dataset, args.session, info, hold_out=held_out)
    print(f"added {args.dataset} to {args.into} as session {args.session}")
    return 0


def _test_sessions(text: str | None) -> list[str]:
    """The names ``--test-sessions A,B`` gives."""
    return [n.strip() for n in text.split(",") if n.strip()] if text else []


def _count(text: str, option: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise UserError(f"{option} {text!r}: expected a number of frames (>= 0) or 'all'")
    return value


PATH_OPTIONS = ("calibration", "videos", "sleap", "nwb", "dlc", "lightning_pose", "openpose", "mmpose",
                "deepfly3d", "skeleton", "dataset")
"""The manifest's options that name files: relative paths are relative to the manifest's folder."""


def _argv(entry: dict[str, Any], folder: Path) -> list[str]:
    """A manifest session's options as ``s3k import`` arguments (``key: value`` -> ``--key value``; a table
    of cameras -> ``CAM=VALUE`` pairs; ``true`` -> the flag)."""
    argv: list[str] = []
    for key, value in entry.items():
        option = "--" + str(key).replace("_", "-")
        here = (lambda v: str(folder / v)) if key in PATH_OPTIONS else str
        if isinstance(value, bool):
            argv += [option] if value else []
        elif isinstance(value, dict):
            argv += [option, *(f"{cam}={here(v)}" for cam, v in value.items())]
        elif isinstance(value, list):
            argv += [option, *(here(v) for v in value)]
        else:
            argv += [option, here(value)]
    return argv


class _ManifestParser(argparse.ArgumentParser):
    """The options of one session of a manifest: a mistake is a one-line error, not an exit."""

    def error(self, message: str):  # type: ignore[override]
        raise UserError(message)


def import_manifest(args: argparse.Namespace) -> int:
    """``s3k import --manifest FILE (--out NEW | --into DATASET)``: every session of the manifest, the first
    one making the new dataset (with ``--out``), each one after added to it."""
    if (args.out is None) == (args.into is None):
        raise UserError(f"--manifest {args.manifest}: give the dataset to write with --out, or the dataset "
                        "to add the sessions to with --into")
    sessions = manifest_sessions(args.manifest)
    held_out = _test_sessions(args.test_sessions)
    unknown = [name for name in held_out if name not in [str(e["session"]) for e in sessions]]
    if unknown:
        raise UserError(f"--test-sessions: {unknown[0]!r} is not a session of {args.manifest}")
    folder = Path(args.manifest).parent
    parser = _ManifestParser(prog=f"s3k import --manifest {args.manifest}")
    configure_parser(parser)
    target = args.into or args.out
    for i, entry in enumerate(sessions):
        where = ["--into", target] if args.into or i else ["--out", target]
        extra = ["--overwrite"] if args.overwrite and not args.into and not i else []
        if str(entry["session"]) in held_out:
            extra += ["--test-sessions", str(entry["session"])]
        try:
            options = parser.parse_args([*_argv(entry, folder), *where, *extra])
        except UserError as exc:
            raise UserError(f"--manifest {args.manifest}: session {entry['session']}: {exc}") from None
        if options.manifest or options.out and options.into:
            raise UserError(f"--manifest {args.manifest}: session {entry['session']}: give no out, into or "
                            "manifest in a session")
        run(options)
        print(f"session {options.session} -> {target}")
    return 0
