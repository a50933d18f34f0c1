"""``s3k validate DATASET``: run every check on a dataset folder and print what is wrong and what is there.

Unlike :meth:`s3k.data.format.Dataset.open`, which stops with the errors of the tables, this collects every
problem (tables, calibration, image files and their pixels), prints each one naming the file, the field and
the line/frame/camera, then a summary: frames per split and labels per keypoint per camera. The exit code is
0 for a usable dataset (warnings allowed unless ``--strict``) and 1 otherwise.
"""

from __future__ import annotations

import argparse
from collections import Counter

from s3k.data.format import SPLITS, Dataset, Problem, check_dataset


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (holds s3k.json)")
    parser.add_argument(
        "--no-images", action="store_true", help="only check that image files exist, do not decode them"
    )
    parser.add_argument("--workers", type=int, default=None, help="image decoding threads (default: CPUs)")
    parser.add_argument(
        "--max-per-field", type=int, default=10, help="print at most this many problems per file and field"
    )
    parser.add_argument("--strict", action="store_true", help="exit non-zero on warnings too")


def _print_problems(problems: list[Problem], limit: int) -> None:
    shown: Counter = Counter()
    hidden: Counter = Counter()
    for p in problems:
        key = (p.severity, p.file if "/" not in p.file else p.file.rsplit("/", 1)[0] + "/*", p.field)
        if shown[key] < limit:
            print(f"{p.severity.upper():7} {p}")
            shown[key] += 1
        else:
            hidden[key] += 1
    for (severity, file, fld), n in hidden.items():
        print(f"{severity.upper():7} {file}: field '{fld}': ... and {n} more like the above")


def _print_summary(ds: Dataset) -> None:
    s = ds.summary()
    W, H = s["image_size"]
    print(
        f"dataset {ds.path}: {s['frames']} frames, {len(ds.cameras)} cameras, {len(ds.keypoints)} keypoints, "
        f"images {W}x{H}, calibration {s['calibration']}, units {s['units']}"
    )
    print("frames per split: " + ", ".join(f"{name} {s['splits'][name]}" for name in SPLITS))
    width = max(len(k) for k in ds.keypoints)
    cam_width = max(6, *(len(c) for c in ds.cameras))
    print(
        "labels (visible, inside the image) per split: "
        + ", ".join(f"{name} {s['labels_per_split'][name]}" for name in SPLITS)
    )
    print("labels per keypoint and camera in the labelled split:")
    print(" " * (width + 2) + " ".join(f"{c:>{cam_width}}" for c in ds.cameras))
    for k in ds.keypoints:
        print(f"  {k:<{width}}" + " ".join(f"{s['labels'][k][c]:>{cam_width}}" for c in ds.cameras))
    n_lab = s["splits"]["labelled"]
    print(
        f"labelled frames with a keypoint labelled in >= 2 cameras (usable for training): "
        f"{s['triangulable_labelled_frames']} of {n_lab}"
    )
    if s["points3d"] is None:
        print("ground-truth 3D points: none")
    else:
        print(f"ground-truth 3D points: {s['points3d']}")


def run(args: argparse.Namespace) -> int:
    problems, dataset = check_dataset(args.dataset, check_images=not args.no_images, workers=args.workers)
    errors = [p for p in problems if p.severity == "error"]
    warnings = [p for p in problems if p.severity == "warning"]
    _print_problems(problems, args.max_per_field)
    if dataset is not None:
        _print_summary(dataset)
    if errors:
        print(f"UNUSABLE: {len(errors)} error(s), {len(warnings)} warning(s) in {args.dataset}")
        return 1
    if warnings and args.strict:
        print(f"FAILED (--strict): {len(warnings)} warning(s) in {args.dataset}")
        return 1
    print(f"OK: {args.dataset} ({len(warnings)} warning(s))")
    return 0
