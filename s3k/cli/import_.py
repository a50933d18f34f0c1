"""`s3k import`: a calibrated recording to a dataset (:func:`s3k.data.recording.import_recording`)."""

from __future__ import annotations

import argparse
import re
from typing import Any

from s3k.cli import examples
from s3k.cli.options import camera_pairs, name, number, parse_crops, parse_size
from s3k.errors import UserError


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
    parser.add_argument("--calibration", required=True,
                        help="anipose calibration.toml, Qualisys .qca.txt, OpenCV/JARVIS .yaml/.xml (a file "
                        "or a folder of one file per camera) or DeepFly3D .pkl; chosen by content")
    parser.add_argument("--videos", nargs="+", required=True, metavar="CAM=FILE",
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
    parser.add_argument("--out", required=True, help="dataset folder to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    parser.add_argument("--labelled", default=None,
                        help="number of labelled frames, or 'all' (default 10, or every frame left after the "
                             "test frames when fewer)")
    parser.add_argument("--test", type=number(int, ge=0), default=0, help="number of test frames (default 0)")
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


def run(args: argparse.Namespace) -> int:
    from s3k.data.recording import import_recording

    videos = camera_pairs(args.videos, "--videos")
    project = args.sleap[0] if args.sleap and len(args.sleap) == 1 and "=" not in args.sleap[0] else None
    if project is not None and not project.lower().endswith(".slp"):
        raise UserError(f"--sleap {project!r}: expected CAMERA=FILE, or one project FILE.slp")
    common: dict[str, Any] = dict(
        sleap=camera_pairs(args.sleap, "--sleap") if args.sleap and project is None else None,
        sleap_project=project, nwb=args.nwb,
        camera_map=camera_pairs(args.camera_map, "--camera-map") if args.camera_map else None,
        accept_predictions=args.accept_predictions,
        dlc=camera_pairs(args.dlc, "--dlc") if args.dlc else None,
        lightning_pose=args.lightning_pose,
        openpose=camera_pairs(args.openpose, "--openpose") if args.openpose else None,
        mmpose=camera_pairs(args.mmpose, "--mmpose") if args.mmpose else None,
        deepfly3d=args.deepfly3d, min_score=args.min_score,
        frame_ids_from=args.frame_ids_from,
        overwrite=args.overwrite,
        labelled=args.labelled if args.labelled in (None, "all") else _count(args.labelled, "--labelled"),
        test=args.test, seed=args.seed, stride=args.stride, min_views=args.min_views,
        size=parse_size(args.size), scale=args.scale,
        crops=parse_crops(args.crop, list(videos)) if args.crop else None,
        units=args.units,
        keypoints=[k.strip() for k in args.keypoints.split(",") if k.strip()] if args.keypoints else None,
        video_regions=parse_crops(args.video_region, list(videos), "--video-region", every=False)
        if args.video_region else None,
        skeleton=args.skeleton,
    )
    if args.sleap_track != "all":
        import_recording(args.calibration, dict(videos), args.out, sleap_track=args.sleap_track, **common)
        return 0
    from pathlib import Path

    from s3k.data.formats.sleap import sleap_tracks

    files = [project] if project else list((common["sleap"] or {}).values())
    if not files:
        raise UserError("--sleap-track all needs SLEAP labels (--sleap)")
    tracks = sleap_tracks(files)
    for i, track in enumerate(tracks):
        folder = track if re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]*", track) else f"track_{i}"
        print(f"track {track} -> {Path(args.out) / folder}")
        import_recording(args.calibration, dict(videos), Path(args.out) / folder, sleap_track=track, **common)
    return 0


def _count(text: str, option: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise UserError(f"{option} {text!r}: expected a number of frames (>= 0) or 'all'")
    return value
