"""`s3k calibrate` on the real sleap-anipose recording, from its four ChArUco board videos alone, against the
acceptance figures: every camera's median reprojection error (with the report s3k calibrate saves beside the
calibration: held-out halves, the triangulated square, coverage, bootstrap spread, warnings); `back`, `mid`,
`top` against the shipped calibration after one similarity transform (camera centres, orientations); the
proofread labels triangulated from `back`, `mid`, `top` reprojected into `side` (median px, full resolution),
with the shipped file too.

Then the references themselves (``held_out``): the board views split in two interleaved folds (optimistic:
the report's contiguous halves are the stricter test), the rig calibrated on one
and the other fold's corners triangulated from every camera but one and reprojected into it (median px), with
the shipped file on the same corners for `back`, `mid`, `top`; the two folds' rigs against each other; and
the proofread labels among `back`, `mid`, `top` alone (each from the other two), ours and the shipped file.

    python benchmarks/calibrate_real.py [--data DIR] [--work /tmp/calibrate-work] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, write_and_emit  # noqa: E402
from s3k.data.formats.anipose import read_anipose_calibration  # noqa: E402
from s3k.data.formats.sleap import read_sleap_analysis  # noqa: E402
from s3k.geometry import Cameras, project, triangulate_pixels  # noqa: E402
from s3k.rigcal.boards import Detections, detect_board, read_board_toml  # noqa: E402
from s3k.rigcal.rig import calibrate_detections  # noqa: E402

CAMS = ["back", "mid", "side", "top"]
DEFAULT = (
    Path(__file__).resolve().parents[1] / "../shared/data/real/sleap-anipose-minimal_session/minimal_session"
)


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``dst ~ s R src + t`` (least squares, Umeyama 1991)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U @ Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean())
    return s, R, md - s * R @ ms


def _angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def compare_to_shipped(ours, shipped, names: list[str]) -> dict:
    """Camera centres and orientations of ``names`` after one similarity ``x_shipped = s Q x_ours + t`` that
    takes our cameras onto the shipped: ``Q`` the rotation average of ``R_shipped^T R_ours`` over the cameras,
    ``s, t`` least squares on the centres given ``Q`` ("poses"); and, for reference, the similarity fitted to
    the three centres alone (Umeyama; its rotation is poorly fixed by three points, "centres_only")."""
    from scipy.spatial.transform import Rotation

    a, b = ours.cameras.numpy(), shipped.cameras.numpy()
    io, js = [ours.index(n) for n in names], [shipped.index(n) for n in names]
    Co = np.stack([-a["R"][i].T @ a["t"][i] for i in io])
    Cs = np.stack([-b["R"][j].T @ b["t"][j] for j in js])
    Q = Rotation.from_matrix(np.stack([b["R"][j].T @ a["R"][i] for i, j in zip(io, js)])).mean().as_matrix()
    u, v = (Co - Co.mean(0)) @ Q.T, Cs - Cs.mean(0)
    s = float((u * v).sum() / (u * u).sum())
    t = Cs.mean(0) - s * Q @ Co.mean(0)
    out: dict = {"poses": {"scale": s}, "centres_only": {}}
    s2, R2, t2 = umeyama(Co, Cs)
    out["centres_only"]["scale"] = s2
    for n, i, j, co, cs in zip(names, io, js, Co, Cs):
        out["poses"][n] = {
            "centre_mm": float(np.linalg.norm(s * Q @ co + t - cs)),
            "orientation_deg": _angle(a["R"][i] @ Q.T @ b["R"][j].T),
        }
        out["centres_only"][n] = {
            "centre_mm": float(np.linalg.norm(s2 * R2 @ co + t2 - cs)),
            "orientation_deg": _angle(a["R"][i] @ R2.T @ b["R"][j].T),
        }
    return out


def labels_into(rig, data: Path, sources: list[str], target: str, per_keypoint: bool = False):
    """Median px distance, in ``target``, between its proofread labels and the labels of ``sources``
    triangulated (unit weights) and reprojected."""
    uv = np.stack(
        [read_sleap_analysis(data / c / f"minimal_{c}_proofread.analysis.h5").uv for c in [*sources, target]],
        1,
    )  # (T, S+1, K, 2)
    idx = [rig.index(c) for c in [*sources, target]]
    cams = Cameras.from_numpy(
        *(rig.cameras.numpy()[k][idx] for k in ("K", "dist", "R", "t")), dtype=torch.float64
    )
    seen = np.isfinite(uv).all(-1)
    src = torch.from_numpy(np.nan_to_num(uv[:, :-1]))
    X, valid = triangulate_pixels(cams[:-1], src, torch.from_numpy(seen[:, :-1] * 1.0))
    ok = valid.numpy() & (seen[:, :-1].sum(1) >= 2) & seen[:, -1]
    proj = project(cams[-1], X)[0].numpy()
    err = np.linalg.norm(proj - uv[:, -1], axis=-1)
    if per_keypoint:
        names = read_sleap_analysis(data / target / f"minimal_{target}_proofread.analysis.h5").keypoints
        return {k: float(np.median(err[:, i][ok[:, i]])) for i, k in enumerate(names) if ok[:, i].any()}
    return float(np.median(err[ok]))


def _calibrate(data: Path, work: Path, name: str, extra: list[str]) -> dict:
    """Run ``s3k calibrate`` (timed) and measure its result."""
    sources = [
        f"{c}={data / c / 'calibration_images' / f'minimal_session-{c}-calibration.MOV'}" for c in CAMS
    ]
    out = work / f"{name}.toml"
    cmd = [
        sys.executable,
        "-m",
        "s3k.cli",
        "calibrate",
        *sources,
        "--board",
        str(data / "board.toml"),
        "--out",
        str(out),
        "--figure",
        str(work / f"{name}.png"),
        "--overwrite",
        *extra,
    ]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    seconds = time.perf_counter() - start
    print(proc.stdout, end="")
    ours = read_anipose_calibration(out)
    shipped = read_anipose_calibration(data / "calibration.toml")
    report = json.loads((work / f"{name}.report.json").read_text())
    return {
        "calibrate_command": shlex.join(["s3k", *cmd[3:]])
        .replace(str(data), "$D")
        .replace(str(work), "$WORK"),
        "calibrate_wall_s": round(seconds, 1),
        "median_reprojection_px": {c: round(report["detections"][c]["median_px"], 2) for c in CAMS},
        "report": report,
        "vs_shipped_back_mid_top": compare_to_shipped(ours, shipped, ["back", "mid", "top"]),
        "labels_back_mid_top_into_side_median_px": labels_into(ours, data, ["back", "mid", "top"], "side"),
        "labels_back_mid_top_into_side_median_px_shipped_file": labels_into(
            shipped, data, ["back", "mid", "top"], "side"
        ),
        "labels_leave_one_out_median_px": {
            c: labels_into(ours, data, [o for o in CAMS if o != c], c) for c in CAMS
        },
        "labels_back_mid_top_into_side_median_px_per_keypoint": labels_into(
            ours, data, ["back", "mid", "top"], "side", per_keypoint=True
        ),
    }


def corners_into(rig, dets: list[Detections], frames: list[int], sources: list[str], target: str) -> float:
    """Median px distance, in ``target``, between its detected board corners of ``frames`` and those of
    ``sources`` triangulated and reprojected (corners every camera saw)."""
    idx = [rig.index(c) for c in [*sources, target]]
    cams = Cameras.from_numpy(
        *(rig.cameras.numpy()[k][idx] for k in ("K", "dist", "R", "t")), dtype=torch.float64
    )
    err: list[np.ndarray] = []
    for f in frames:
        seen = [dict(zip(*dets[CAMS.index(c)].frames[f])) for c in [*sources, target]]
        ids = sorted(set.intersection(*(set(s) for s in seen)))
        if len(ids) < 4:
            continue
        uv = torch.from_numpy(np.stack([[s[i] for i in ids] for s in seen[:-1]])[None])
        X, _ = triangulate_pixels(cams[:-1], uv, torch.ones(uv.shape[:3], dtype=torch.float64))
        err.append(np.linalg.norm(project(cams[-1], X)[0].numpy()[0] - [seen[-1][i] for i in ids], axis=-1))
    return float(np.median(np.concatenate(err)))


def held_out(data: Path, ours) -> dict:
    """The board views in two folds: each fold's corners against the rig calibrated on the other (every camera
    from the other three; back, mid, top from the other two, ours and the shipped file), the two folds' rigs
    against each other, and the labels among back, mid, top with ``ours`` (the whole rig) and the shipped
    file."""
    board = read_board_toml(data / "board.toml")
    dets = [
        detect_board(data / c / "calibration_images" / f"minimal_session-{c}-calibration.MOV", board)
        for c in CAMS
    ]
    frames = sorted(set.intersection(*(set(d.frames) for d in dets)))
    shipped = read_anipose_calibration(data / "calibration.toml")
    three = ["back", "mid", "top"]
    out: dict = {"views": len(frames), "folds": []}
    rigs = []
    for fold in range(2):
        test = frames[fold::2]
        train = [
            Detections({f: v for f, v in d.frames.items() if f not in test}, d.size, d.images, d.marker_ids)
            for d in dets
        ]
        rig = calibrate_detections(CAMS, train, board).rig()
        rigs.append(rig)
        out["folds"].append(
            {
                "held_out_views": len(test),
                "into_each_from_other_three_px": {
                    c: corners_into(rig, dets, test, [o for o in CAMS if o != c], c) for c in CAMS
                },
                "among_back_mid_top_px": {
                    c: corners_into(rig, dets, test, [o for o in three if o != c], c) for c in three
                },
                "among_back_mid_top_px_shipped_file": {
                    c: corners_into(shipped, dets, test, [o for o in three if o != c], c) for c in three
                },
            }
        )
    out["fold_rigs_against_each_other"] = compare_to_shipped(rigs[0], rigs[1], CAMS)["poses"]
    out["labels_among_back_mid_top_px"] = {
        c: labels_into(ours, data, [o for o in three if o != c], c) for c in three
    }
    out["labels_among_back_mid_top_px_shipped_file"] = {
        c: labels_into(shipped, data, [o for o in three if o != c], c) for c in three
    }
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(DEFAULT), help="the recording folder")
    p.add_argument("--work", default="/tmp/calibrate-work", help="where the calibrations and pictures go")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)
    data, work = Path(a.data).resolve(), Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    labels = [f"{c}={data / c / f'minimal_{c}_proofread.analysis.h5'}" for c in CAMS]
    result = {
        "command": "python benchmarks/calibrate_real.py",
        "revision": git_revision(),
        "board_only": _calibrate(data, work, "calibration", []),
        "board_and_labels": _calibrate(data, work, "calibration_labels", ["--labels", *labels]),
        "held_out": held_out(data, read_anipose_calibration(work / "calibration.toml")),
    }
    write_and_emit(result, a.out)


if __name__ == "__main__":
    main()
