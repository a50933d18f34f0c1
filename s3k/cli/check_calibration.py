"""``s3k check-calibration DATASET``: per-camera reprojection residuals from the labels, the cameras
inconsistent with the others (:mod:`s3k.geometry.consistency`), and their recalibration from ChArUco frames
(:mod:`s3k.rigcal.recalibration`)."""

from __future__ import annotations

import argparse
import glob
import logging

import numpy as np

from s3k.base.errors import UserError
from s3k.base.outputs import check_output
from s3k.cli import examples
from s3k.cli.options import camera_pairs, number
from s3k.data import Dataset
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.validate import frame_offset_lines
from s3k.geometry.consistency import CalibrationCheck, check_calibration, reprojection_residuals
from s3k.rigcal.recalibration import recalibrate_dataset

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Triangulate the dataset's 2D labels and report each camera's reprojection residual, a leave-one-"
        "camera-out check, and the cameras inconsistent with the others (exit code 2 when any). Optionally "
        "recalibrate a camera from ChArUco frames and show the residual after the fix."
    )
    parser.epilog = examples("s3k check-calibration data/session",
                             "s3k check-calibration data/session --recalibrate flagged "
                             "--write-calibration calibration_fixed.toml")
    parser.add_argument("dataset", help="dataset folder (s3k import or s3k simulate)")
    parser.add_argument(
        "--splits", default="labelled,test",
        help="comma-separated splits whose labels are used (default: labelled,test)",
    )
    parser.add_argument("--factor", type=number(gt=0), default=3.0,
                        help="flag a camera whose leave-one-out residual exceeds FACTOR x the others' "
                        "(default 3)")
    parser.add_argument("--min-px", type=number(ge=0), default=None,
                        help="never flag a camera whose residual is below this many pixels "
                        "(default: 0.5%% of the image diagonal)")
    fix = parser.add_argument_group("recalibration from ChArUco frames")
    fix.add_argument("--recalibrate", nargs="+", default=None, metavar="CAM",
                     help="cameras to recalibrate ('flagged': those the check names; default: none)")
    fix.add_argument("--calibration", default=None,
                     help="the recording's anipose calibration.toml (default: the one the dataset was "
                     "imported from)")
    fix.add_argument("--board", default=None, help="anipose board.toml (default: beside the calibration)")
    fix.add_argument("--charuco", nargs="+", default=None, metavar="CAM=GLOB",
                     help="calibration images per camera (default: <calibration dir>/<camera>/"
                     "calibration_images/*.jpg); files of one board position share their last number")
    fix.add_argument("--write-calibration", default=None, metavar="TOML",
                     help="write the calibration with the recalibrated cameras (anipose format, full "
                     "resolution); never over the calibration read or a dataset's file (default: not "
                     "written)")
    fix.add_argument("--overwrite", action="store_true", help="replace --write-calibration if it exists")
    fix.add_argument("--force", action="store_true",
                     help="keep (and write) a recalibration that raises the labels' median residual by more "
                     "than 20%% and 0.5 px (refused by default)")


WORSE_FACTOR, WORSE_PX = 1.2, 0.5
"""A recalibration is worse than the calibration when it raises the labels' median residual above both
``WORSE_FACTOR`` times and ``WORSE_PX`` pixels more than before (a repair from good board images moves it by
hundredths of a pixel; one from another camera's images by tens of pixels)."""


def _median_residual(cams, uv, mask) -> float:
    """The median pixel residual of every label against the point triangulated from all its views."""
    res = reprojection_residuals(cams, uv, mask)
    return float(np.nanmedian(res)) if np.isfinite(res).any() else float("nan")


def _worse(before: CalibrationCheck, after: CalibrationCheck, old: float, new: float, targets: list[str],
           writing: bool) -> str:
    """The refusal of a repair that raised the labels' residuals: the cameras recalibrated, the residual
    before and after, and the camera whose own residual rose the most."""
    rise = {a.name: (b.median_px, a.median_px) for b, a in zip(before.cameras, after.cameras)
            if np.isfinite(b.median_px) and np.isfinite(a.median_px)}
    worst = max(rise, key=lambda c: rise[c][1] / max(rise[c][0], 1e-9)) if rise else None
    camera = f" (camera {worst}: {rise[worst][0]:.2f} -> {rise[worst][1]:.2f} px)" if worst else ""
    return (f"recalibrating {', '.join(targets)} raised the labels' median residual from {old:.2f} px to "
            f"{new:.2f} px{camera}: the repair is worse than the calibration"
            + ("; nothing written" if writing else ""))


def _recalibrate(args, ds, ids, uv, mask, before: CalibrationCheck) -> int:
    targets = before.inconsistent if args.recalibrate == ["flagged"] else list(args.recalibrate)
    if not targets:
        print("recalibration: no camera to recalibrate")
        return 0
    patterns = camera_pairs(args.charuco, "--charuco") if args.charuco else None
    fixed = recalibrate_dataset(ds, ids, targets, before.inconsistent, calibration=args.calibration,
                                board=args.board, charuco=patterns)
    for cam, fix in fixed.fixes.items():
        print(f"recalibrated {cam} from {fixed.frames[cam]} ChArUco frames: intrinsics rms "
              f"{fix.intrinsics_rms_px:.2f} px; bundle-adjusted with {', '.join(fixed.reference)} held "
              "fixed: "
              f"f {fix.K[0, 0]:.1f} px, k1 {fix.dist[0]:.3f}, {fix.corners} board corners in {fix.frames} "
              f"frames, median {fix.pose_median_px:.2f} px")
    check = check_calibration(fixed.cameras, uv, mask, list(ds.cameras), factor=args.factor,
                              min_px=args.min_px, image_size=ds.image_size)
    print(f"after recalibrating {', '.join(targets)}:")
    print(check.format())
    old = _median_residual(ds.calibration(ids, dtype=np.float64), uv, mask)
    new = _median_residual(fixed.cameras, uv, mask)
    if new > max(WORSE_FACTOR * old, old + WORSE_PX):  # NaN (no label triangulates): nothing to judge by
        message = _worse(before, check, old, new, targets, bool(args.write_calibration))
        if not args.force:
            raise UserError(message, hint="check the --charuco images of "
                            f"{', '.join(targets)}, or pass --force to keep the repair anyway")
        log.warning("%s (kept: --force)", message.removesuffix("; nothing written"))
    if args.write_calibration:
        write_anipose_calibration(args.write_calibration, fixed.rig)
        print(f"wrote {args.write_calibration}")
    return 2 if check.inconsistent else 0


def _no_labels(ds, path: str, splits: list[str], n_frames: int) -> tuple[str, str]:
    """The error (and hint) for splits without a keypoint labelled in two cameras of a frame: the check
    triangulates 2D labels, so it needs labelled or test frames."""
    chosen = ", ".join(splits) or "(none)"
    what = (f"{path}: the {n_frames} frames of {chosen} have no keypoint labelled in two cameras" if n_frames
            else f"{path}: no frames in {chosen}")
    others = [s for s in ("labelled", "test") if s not in splits and len(ds.frames(s))
              and (ds.labels(ds.frames(s))[1].sum(axis=1) >= 2).any()]
    if others:
        return (f"{what}; the check triangulates 2D labels", f"use the {' and '.join(others)} frames: "
                f"--splits {','.join(others)}")
    return (f"{what}, and the dataset has no labelled or test frame with one: the check triangulates 2D "
            "labels of a keypoint seen by two cameras",
            "import the recording with its labels (docs/importing.md), or label frames with s3k label")


def run(args: argparse.Namespace) -> int:
    if args.write_calibration:
        charuco = camera_pairs(args.charuco, "--charuco") if args.charuco else {}
        check_output(args.write_calibration, args.overwrite, inputs={
            "--calibration": args.calibration, "--board": args.board,
            "--charuco": [f for pattern in charuco.values() for f in glob.glob(pattern)]},
            option="--write-calibration")
    ds = Dataset.open(args.dataset)
    splits = [s.strip() for s in args.splits.split(",") if s.strip()]
    unknown = [s for s in splits if s not in ("labelled", "unlabelled", "test")]
    if unknown:
        raise UserError(f"--splits: unknown split {unknown[0]!r}; choose from labelled, unlabelled, test")
    ids = np.concatenate([np.asarray(ds.frames(s)) for s in splits]) if splits else np.zeros(0, int)
    uv, mask = ds.labels(ids)
    if not (mask.sum(axis=1) >= 2).any():
        raise UserError(*_no_labels(ds, args.dataset, splits, len(ids)))
    cams = ds.calibration(ids, dtype=np.float64)
    print(f"{args.dataset}: {len(ds.cameras)} cameras, {len(ids)} frames ({', '.join(splits)}), "
          f"{int(mask.sum())} labels, image {ds.image_size[0]}x{ds.image_size[1]} px")
    check = check_calibration(
        cams, uv, mask, list(ds.cameras), factor=args.factor, min_px=args.min_px, image_size=ds.image_size
    )
    print(check.format())
    for severity, line in frame_offset_lines(ds):  # a camera out of step looks like a miscalibrated one
        if severity == "warning":
            log.warning(line)
        else:
            print(line)
    if args.recalibrate:
        return _recalibrate(args, ds, ids, uv, mask, check)
    if check.inconsistent or check.notes:
        which = "flagged" if check.inconsistent else "CAM"
        print(f"repair: s3k check-calibration {args.dataset} --recalibrate {which} (recalibrates "
              f"{'the named cameras' if check.inconsistent else 'a camera'} from the recording's ChArUco "
              "frames), or import the recording without them")
    return 2 if check.inconsistent else 0
