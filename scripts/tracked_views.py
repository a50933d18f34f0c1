"""Draw 3D keypoints tracked by ``s3k track`` on the views of a dataset of the same recording.

Each tracked 3D point is projected into every camera of the dataset's (static) calibration and drawn as a
filled dot; the dataset's own 2D labels of that frame, when it has any, are drawn as rings, so a test frame
shows tracked (dot) against proofread (ring). One row per frame, one column per camera.

    python scripts/tracked_views.py --data DATASET --csv tracked.csv --frames 1,59,117 --out views.jpg
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from s3k.data import Dataset
from s3k.data.tracks_csv import read_csv
from s3k.geometry import project


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, type=Path, help="dataset folder (static calibration)")
    p.add_argument("--csv", required=True, type=Path, help="3D CSV written by 's3k track'")
    p.add_argument("--frames", required=True, help="comma-separated dataset frame ids to draw")
    p.add_argument("--zoom", type=int, default=2, help="image magnification (default 2)")
    p.add_argument("--out", required=True, type=Path, help="image to write (.png, or .jpg for a small file)")
    a = p.parse_args(argv)

    ds = Dataset.open(a.data)
    tracked = read_csv(a.csv, list(ds.keypoints))
    cams = ds.rig(dtype=np.float64)
    video_frame = ({int(f): int(v) for f, v in zip(ds.frames(), ds.column("video_frame"))}
                   if "video_frame" in ds.frame_columns else {})
    frames = [int(f) for f in a.frames.split(",")]
    hues = np.uint8([[i * 230 // max(1, len(ds.keypoints) - 1)] for i in range(len(ds.keypoints))])
    colours = [tuple(int(c) for c in bgr) for bgr in cv2.applyColorMap(hues, cv2.COLORMAP_HSV)[:, 0]]
    rows = []
    for fid in frames:
        fnum = video_frame.get(fid, fid)
        if fnum not in tracked:
            raise SystemExit(f"{a.csv}: no row with fnum {fnum} (dataset frame {fid})")
        X = torch.from_numpy(tracked[fnum])
        ok = torch.isfinite(X).all(-1)
        uv, depth = project(cams, torch.nan_to_num(X).expand(len(ds.cameras), -1, -1))
        img = ds.images([fid])[0]
        lab_uv, lab_mask = ds.labels([fid])
        tiles = []
        for c, name in enumerate(ds.cameras):
            t = cv2.resize(cv2.cvtColor(img[c], cv2.COLOR_RGB2BGR), None, fx=a.zoom, fy=a.zoom,
                           interpolation=cv2.INTER_CUBIC)
            for k in range(len(ds.keypoints)):
                if lab_mask[0, c, k]:
                    u, v = (lab_uv[0, c, k] * a.zoom).round().astype(int)
                    cv2.circle(t, (int(u), int(v)), 2 * a.zoom, colours[k], 1, cv2.LINE_AA)
                if ok[k] and depth[c, k] > 0:
                    u, v = (uv[c, k].numpy() * a.zoom).round().astype(int)
                    cv2.circle(t, (int(u), int(v)), a.zoom, colours[k], -1, cv2.LINE_AA)
            title = f"{name} frame {fnum} ({ds.split_of([fid])[0]})"
            cv2.putText(t, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(t)
        rows.append(np.concatenate(tiles, axis=1))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 85] if a.out.suffix.lower() in (".jpg", ".jpeg") else []
    if not cv2.imwrite(str(a.out), np.concatenate(rows, axis=0), params):
        raise SystemExit(f"{a.out}: could not write the image (unknown extension?)")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
