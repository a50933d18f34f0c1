"""3D error of keypoints tracked by ``s3k track`` against the proofread 2D labels of the same recording.

The proofread labels of all cameras are triangulated (unit weights, full-resolution pixels, the given
calibration) and compared with the tracked 3D points, split by the dataset's frame splits (the labelled frames
were training data; test and unlabelled frames were not labelled for training). Prints one JSON object:
median and RMS distance per split, in the calibration's units, and the number of points compared.

    python scripts/tracked_vs_labels.py --csv tracked.csv --calibration calibration.toml --data DATASET \
        --sleap back=back.analysis.h5 mid=... side=... top=...
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from s3k.data import Dataset
from s3k.data.formats.anipose import read_anipose_calibration
from s3k.data.formats.sleap import read_sleap_analysis
from s3k.data.tracks_csv import read_csv
from s3k.geometry import triangulate_pixels


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--csv", required=True, help="3D CSV written by 's3k track'")
    p.add_argument("--calibration", required=True, help="anipose calibration.toml used for tracking")
    p.add_argument("--data", required=True, help="the imported dataset (for its frame splits)")
    p.add_argument("--sleap", nargs="+", required=True, metavar="CAM=FILE",
                   help="SLEAP analysis file per camera")
    a = p.parse_args(argv)

    rig = read_anipose_calibration(a.calibration)
    files = dict(s.split("=", 1) for s in a.sleap)
    missing = [c for c in rig.names if c not in files]
    if missing:
        raise SystemExit(f"--sleap: no file for camera(s) {', '.join(missing)}")
    tables = [read_sleap_analysis(files[c]) for c in rig.names]
    keypoints = list(tables[0].keypoints)
    uv = np.stack([t.uv for t in tables], axis=1)  # (T, C, K, 2), NaN where not placed
    seen = np.isfinite(uv).all(-1)
    cams = rig.cameras
    X, valid = triangulate_pixels(cams, torch.from_numpy(np.nan_to_num(uv)), torch.from_numpy(seen * 1.0))
    X, valid = X.numpy(), valid.numpy() & (seen.sum(1) >= 2)

    tracked = read_csv(a.csv, keypoints)
    ds = Dataset.open(a.data)
    video = ds.column("video_frame").astype(int) if "video_frame" in ds.frame_columns else ds.frames()
    split = dict(zip(video.tolist(), ds.split_of(ds.frames()).tolist()))
    dist: dict[str, list[float]] = {}
    for fnum, xyz in tracked.items():
        if fnum >= len(X):
            continue
        ok = valid[fnum] & np.isfinite(xyz).all(-1)
        d = np.linalg.norm(xyz[ok] - X[fnum][ok], axis=-1)
        for name in (split.get(fnum, "not imported"), "all"):
            dist.setdefault(name, []).extend(d.tolist())
    out = {name: {"median": float(np.median(v)), "rms": float(np.sqrt(np.mean(np.square(v)))),
                  "points": len(v)} for name, v in dist.items() if v}
    print(json.dumps({"units": rig.units, "reference": "proofread labels triangulated from all cameras",
                      "per_split": out}))


if __name__ == "__main__":
    main()
