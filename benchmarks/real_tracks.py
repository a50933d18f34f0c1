"""Filtered tracks and one round of the way back on the real recording (docs/tracks.md).

1. ``s3k track`` tracks the recording's four videos with RUN (offline Kalman filter on, the SLEAP
   skeleton's limbs held near their lengths), and the raw and filtered points are compared: frame-to-frame
   jitter (median norm of the second difference, mm per frame squared) and the 3D error against the
   proofread labels triangulated from all four cameras (the calibration given; median and RMS, mm), on the
   test frames and on all frames.
2. With ``--loop``: a copy of DATA gets the ``--worst`` frames of the track's doubt ranking (``s3k
   add-frames``), labelled from the proofread labels as a stand-in for a person (through the labelling app's
   store, as its clicks would be), RUN is fine-tuned on it (``s3k train --init-from RUN``), and the test
   frames' 3D error is measured again. With ``--control`` RUN is also trained on as long on an unchanged copy
   of DATA, so that what the new labels bring is told from what more steps bring.

Example::

    python benchmarks/real_tracks.py --run runs/real/run-s3k --data runs/real/crop \\
        --calibration runs/real/calibration_fixed.toml --work /tmp/real-tracks --loop --control \\
        --out docs/results/tracks/real.json
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import fine_tune_args, git_revision, write_and_emit  # noqa: E402

CAMERAS = ("back", "mid", "side", "top")


def recording_files(recording: Path) -> tuple[dict[str, Path], dict[str, Path]]:
    videos = {c: recording / c / f"minimal_{c}.mp4" for c in CAMERAS}
    sleap = {c: recording / c / f"minimal_{c}_proofread.analysis.h5" for c in CAMERAS}
    return videos, sleap


def proofread_points(sleap: dict[str, Path], calibration: Path, check_px: float | None = None
                     ) -> tuple[list[str], np.ndarray, dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """``(keypoints, X (T, K, 3), uv {camera: (T, K, 2)}, without {camera: X'}, offsets {camera: (T, K)})``:
    the proofread labels triangulated from every camera that has them (NaN where fewer than two), the labels
    themselves (full-resolution pixels), per camera the points triangulated without that camera's labels (how
    far the reference moves when one view's clicks are left out: its own uncertainty), and each label's
    distance from the other cameras' agreement (full-resolution pixels; NaN where that cannot be told).
    ``check_px``: leave out of the triangulations the labels more than that from the other cameras'
    agreement (:func:`disagreeing`); ``uv`` keeps them all."""
    import torch

    from s3k.base.label_reference import leave_one_view_out
    from s3k.data.formats.anipose import read_anipose_calibration
    from s3k.data.formats.sleap import read_sleap_analysis
    from s3k.geometry import triangulate_pixels

    rig = read_anipose_calibration(calibration)
    tables = {c: read_sleap_analysis(sleap[c]) for c in rig.names}
    keypoints = list(tables[rig.names[0]].keypoints)
    uv = np.stack([tables[c].uv for c in rig.names], axis=1)  # (T, C, K, 2)
    seen = np.isfinite(uv).all(-1)
    # each label's distance from the other cameras' agreement (the labelling app's check); NaN: cannot be told
    off = leave_one_view_out(rig.cameras.reshape(1, -1), np.nan_to_num(uv), seen)
    offsets = {c: off[:, i] for i, c in enumerate(rig.names)}
    if check_px is not None:
        flagged = disagreeing(offsets, check_px)
        seen &= ~np.stack([flagged[c] for c in rig.names], axis=1)

    def triangulated(use: np.ndarray) -> np.ndarray:
        X, valid = triangulate_pixels(rig.cameras, torch.from_numpy(np.nan_to_num(uv)),
                                      torch.from_numpy(use * 1.0))
        return np.where((valid.numpy() & (use.sum(1) >= 2))[..., None], X.numpy(), np.nan)

    without = {}
    for i, c in enumerate(rig.names):
        use = seen.copy()
        use[:, i] = False
        without[c] = triangulated(use)
    return keypoints, triangulated(seen), {c: tables[c].uv for c in rig.names}, without, offsets


def skeleton_of(sleap_file: Path) -> list[str]:
    """The SLEAP file's edges as ``A,B`` (the dataset's skeleton, which the import does not yet keep)."""
    import h5py

    with h5py.File(sleap_file, "r") as f:
        return [f"{a.decode()},{b.decode()}" for a, b in f["edge_names"][:]]


def track(run: Path, videos: dict[str, Path], calibration: Path, out: Path, limbs: list[str],
          again: bool = False) -> None:
    """``s3k track`` RUN into ``out``, unless ``out`` is already its track (``again``: track anyway)."""
    from s3k import cli
    from s3k.data.tracks_csv import tracked_with

    if not again and tracked_with(out, run):
        print(f"{out}: already tracked with {run}'s present weights (--retrack to track again)")
        return

    args = ["track", str(run), "--videos", *[f"{c}={p}" for c, p in videos.items()], "--calibration",
            str(calibration), "--min-weight", "0.5", "--out", str(out), "--overwrite", "--no-progress"]
    if limbs:
        args += ["--filter-limbs", *limbs]
    if cli.main(args) != 0:
        raise SystemExit(f"s3k track {run} failed")


def compare(csv_path: Path, keypoints: list[str], truth: np.ndarray, splits: dict[int, str]) -> dict:
    """Raw and filtered points of a track against ``truth``: jitter and errors per split, mm, and the
    filtered minus the raw on the test frames (paired, with bootstrap intervals). The test frames' error
    arrays ``(T, K)`` (NaN elsewhere) are kept under ``_test_errors`` for :func:`paired`."""
    from s3k.data.tracks_csv import read_csv
    from s3k.experiments.track_filter import errors, jitter, paired_difference
    from s3k.inference.track_filter import raw_path

    out: dict = {"_test_errors": {}}
    raw_pts = read_csv(raw_path(csv_path), keypoints)
    filt_pts = read_csv(csv_path, keypoints)
    frames = sorted(raw_pts)
    raw = np.stack([raw_pts[f] for f in frames])
    filt = np.stack([filt_pts[f] for f in frames])
    ref = truth[frames]
    placed = np.isfinite(raw).all(-1)
    split = np.array([splits.get(f, "not imported") for f in frames])
    for name, X in (("raw", raw), ("filtered", filt)):
        out[name] = {"jitter_mm_per_frame2": jitter(X), "all": errors(X, ref, 1.0, placed)}
        for s in ("test", "labelled", "unlabelled"):
            out[name][s] = errors(X, ref, 1.0, placed & (split == s)[:, None])
        err = np.linalg.norm(X - ref, axis=-1)
        out["_test_errors"][name] = np.where(placed & (split == "test")[:, None], err, np.nan)
        with np.errstate(all="ignore"):
            medians = np.nanmedian(out["_test_errors"][name], axis=0)
        out[name]["test_median_per_keypoint"] = {k: float(m) for k, m in zip(keypoints, medians)}
    out["filtered_minus_raw_test"] = paired_difference(out["_test_errors"]["raw"],
                                                       out["_test_errors"]["filtered"])
    return out


def paired(before: dict, after: dict) -> dict:
    """``after`` minus ``before`` on the test frames, raw and filtered points (two :func:`compare` results
    of tracks of the same frames)."""
    from s3k.experiments.track_filter import paired_difference

    return {name: paired_difference(before["_test_errors"][name], after["_test_errors"][name])
            for name in ("raw", "filtered")}


def public(result: dict) -> dict:
    """``result`` without the ``_``-keys (arrays), at any depth."""
    if isinstance(result, dict):
        return {k: public(v) for k, v in result.items() if not k.startswith("_")}
    return result


def disagreeing(offsets: dict[str, np.ndarray], max_px: float) -> dict[str, np.ndarray]:
    """``{camera: (T, K) bool}``: the labels more than ``max_px`` from the other cameras' agreement."""
    return {c: np.nan_to_num(off, nan=0.0) > max_px for c, off in offsets.items()}


def label_from_proofread(data: Path, frames: list[int], uv: dict[str, np.ndarray],
                         keypoints: list[str], left_out: dict[str, np.ndarray] | None = None) -> int:
    """Label the dataset's ``frames`` with the proofread labels of their video frames, mapped onto the
    dataset's images as its import mapped them, through the labelling app's store; returns the labels.
    ``left_out`` (:func:`disagreeing`): labels a person would have corrected, not written."""
    from s3k.data import Dataset
    from s3k.detector.geometry_record import dataset_geometry
    from s3k.geometry.warp import crop_resize_matrix
    from s3k.label.store import Edit, LabelStore

    ds = Dataset.open(data, cache="none")
    geometry = dataset_geometry(ds)
    video = dict(zip(ds.frames().tolist(), ds.column("video_frame").astype(int).tolist()))
    W, H = ds.image_size
    store = LabelStore.open(data, labeller="proofread (stand-in for a person)")
    n = 0
    for f in frames:
        edits = []
        for cam in ds.cameras:
            M = crop_resize_matrix(tuple(geometry["cameras"][cam]["box"]), ds.image_size)
            for k, kp in enumerate(keypoints):
                if kp not in ds.keypoints:
                    continue
                p = uv[cam][video[f], k]
                if not np.isfinite(p).all() or (left_out is not None and left_out[cam][video[f], k]):
                    continue
                u, v = (M @ np.array([p[0], p[1], 1.0]))[:2]
                if -0.5 <= u <= W - 0.5 and -0.5 <= v <= H - 0.5:
                    edits.append(Edit(cam, kp, float(u), float(v)))
        if edits:
            store.save(f, edits, store.version(f), source="proofread")
            n += len(edits)
    return n


def fine_tune(run: Path, data: Path, out: Path, steps: int, lr: float | None,
              seed: int | None = None) -> None:
    """``s3k train DATA --out OUT --init-from RUN --steps STEPS``: RUN's configuration continued where it
    ended (each pass at its final learning rate, the self-supervised term on from the start), at ``lr``
    instead where given; ``seed`` (batches, augmentation) instead of RUN's. The same call continues a begun
    OUT and keeps a finished one (:func:`benchmarks.common.fine_tune_args`)."""
    from s3k import cli

    args = fine_tune_args(data, run, out, steps, lr=lr, seed=seed, validate=False)
    if cli.main(args) != 0:
        raise SystemExit(f"s3k train {out} failed")


def copy_dataset(data: Path, to: Path) -> Path:
    if not (to / "s3k.json").is_file():
        shutil.copytree(data, to, ignore=shutil.ignore_patterns(".cache"))
    return to


def loop(a, videos, sleap, keypoints, truth, splits, limbs, uv, offsets, before: dict) -> dict:
    """One round of the way back (module docstring)."""
    from s3k import cli
    from s3k.label.queue import read_queue

    work = Path(a.work)
    data = work / "data-loop"
    # the labels a careful person would have corrected, over the whole recording
    flagged = None if a.label_check is None else disagreeing(offsets, a.label_check)
    if not (data / "label-queue.csv").is_file():
        copy_dataset(Path(a.data), data)
        if cli.main(["add-frames", str(work / "tracked.csv"), "--data", str(data), "--worst", str(a.worst),
                     "--spacing", str(a.spacing)]) != 0:
            raise SystemExit("s3k add-frames failed")
        queued = [int(r["frame"]) for r in read_queue(data)]
        labels = label_from_proofread(data, queued, uv, keypoints, flagged)
    else:  # added and labelled by an earlier call: the labels its frames hold now
        from s3k.label.store import LabelStore

        queued = [int(r["frame"]) for r in read_queue(data)]
        store = LabelStore.open(data)
        labels = int(sum(store.arrays(f)[1].sum() for f in queued))
    result = {"worst": a.worst, "queued_frames": queued, "labels_added": labels, "steps": a.steps, "lr": a.lr,
              "label_check_px": a.label_check}
    if flagged is not None:
        result["label_check_frames_left_out"] = {
            cam: {k: int(n) for k, n in zip(keypoints, mask.sum(0)) if n} for cam, mask in flagged.items()}
    reading = (videos, limbs, keypoints, truth, splits)
    result["after"] = tune_and_compare(a, data, "tuned", None, *reading)
    result["after_minus_before_test"] = paired(before, result["after"])
    if a.control:
        control = copy_dataset(Path(a.data), work / "data-control")
        result["continued_without_new_labels"] = tune_and_compare(a, control, "continued", None, *reading)
        result["after_minus_continued_test"] = paired(result["continued_without_new_labels"],
                                                      result["after"])
    if a.repeats > 1:
        result["repeats"] = repeats(a, data, reading, before, result)
    return result


def tune_and_compare(a, data: Path, name: str, seed: int | None, videos, limbs, keypoints, truth,
                     splits) -> dict:
    """RUN fine-tuned on ``data`` into WORK/run-NAME (``seed``: None for RUN's), the recording tracked with
    it into WORK/tracked-NAME.csv, and that track against the reference (:func:`compare`)."""
    work = Path(a.work)
    fine_tune(Path(a.run), data, work / f"run-{name}", a.steps, a.lr, seed)
    track(work / f"run-{name}", videos, Path(a.calibration), work / f"tracked-{name}.csv", limbs, a.retrack)
    return compare(work / f"tracked-{name}.csv", keypoints, truth, splits)


def repeats(a, data: Path, reading: tuple, before: dict, first: dict) -> dict:
    """The loop's fine-tuning (and with ``--control`` the control's) done ``--repeats`` times, each with its
    own seed (RUN's seed + r: batches and augmentation), on the same added frames and labels: what the new
    labels do, told from where one fine-tuning happens to end. Per repeat the test frames' raw median, 90th
    percentile and RMS of each model and the paired differences; over repeats their mean and 95%
    t-interval. ``reading``: :func:`tune_and_compare`'s ``(videos, limbs, keypoints, truth, splits)``."""
    from benchmarks.common import t_interval

    keypoints = reading[2]
    from s3k.run_folder import RunFolder

    cfg = RunFolder(a.run).config()
    assert cfg is not None, f"{a.run}: no configuration recorded"
    base = cfg.execution.seed
    rows = []
    for r in range(a.repeats):
        if r == 0:
            after, control = first["after"], first.get("continued_without_new_labels")
        else:
            after = tune_and_compare(a, data, f"tuned-r{r}", base + r, *reading)
            control = None
            if a.control:
                control = tune_and_compare(a, Path(a.work) / "data-control", f"continued-r{r}", base + r,
                                           *reading)
        gain = paired(before, after)["raw"]
        row = {"seed": base + r, "after": after["raw"]["test"],
               "after_minus_before": {k: gain[k] for k in ("median", "rms", "p90")}}
        if control is not None:
            gain = paired(control, after)["raw"]
            row["control"] = control["raw"]["test"]
            row["after_minus_control"] = {k: gain[k] for k in ("median", "rms", "p90")}
            row["after_minus_control_median_per_keypoint"] = {
                k: after["raw"]["test_median_per_keypoint"][k] - control["raw"]["test_median_per_keypoint"][k]
                for k in keypoints}
        rows.append(row)
    over: dict = {}
    for what in ("after_minus_before", "after_minus_control"):
        for k in ("median", "rms", "p90"):
            values = [row[what][k] for row in rows if what in row]
            if values:
                over[f"{what}_{k}_mm"] = {"mean": float(np.mean(values)), "ci95": t_interval(values),
                                          "per_repeat": values}
    per_keypoint = [row["after_minus_control_median_per_keypoint"] for row in rows
                    if "after_minus_control_median_per_keypoint" in row]
    if per_keypoint:  # each keypoint's test-frame median, after minus control, mean over the repeats
        over["after_minus_control_median_per_keypoint_mm"] = {
            k: float(np.mean([d[k] for d in per_keypoint])) for k in keypoints}
    return {"per_repeat": rows, "over_repeats": over}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a finished run of 's3k train' on DATA")
    p.add_argument("--data", required=True, help="the recording's dataset (not changed: the loop copies it)")
    p.add_argument("--calibration", required=True, help="the calibration the dataset was imported with")
    p.add_argument("--recording", default="../shared/data/real/sleap-anipose-minimal_session/minimal_session")
    p.add_argument("--work", required=True, help="folder for the tracks, the copies and the runs")
    p.add_argument("--loop", action="store_true", help="one round of the way back (module docstring)")
    p.add_argument("--control", action="store_true", help="also train as long without the new labels")
    p.add_argument("--worst", type=int, default=10, help="frames to add and label (default 10)")
    p.add_argument("--spacing", type=int, default=2, help="s3k add-frames --spacing (default 2)")
    p.add_argument("--steps", type=int, default=300, help="fine-tuning steps (default 300)")
    p.add_argument("--lr", type=float, default=None,
                   help="fine-tuning learning rate (default: each pass's final one, as s3k train "
                        "--init-from takes it)")
    p.add_argument("--label-check", type=float, default=None, metavar="PX",
                   help="the stand-in for a person leaves out a proofread label more than PX full-resolution "
                        "pixels from where the other cameras' labels put it, as the labelling app's check "
                        "would show it (default: every label written)")
    p.add_argument("--reference-check", type=float, default=None, metavar="PX",
                   help="the reference leaves out the proofread labels more than PX full-resolution pixels "
                        "from where the other cameras' labels put them (the --label-check rule) and is "
                        "triangulated from the rest (default: from every label)")
    p.add_argument("--repeats", type=int, default=1,
                   help="fine-tune (and control) this many times, seeds RUN's + 0, 1, ..., on the same new "
                        "labels, and report the differences over them (default 1)")
    p.add_argument("--retrack", action="store_true",
                   help="track again even where WORK holds a track of the run's present weights (default: "
                        "reuse it, so that a rerun costs only what changed)")
    p.add_argument("--out", default=None, help="JSON file to write")
    a = p.parse_args(argv)
    if a.repeats < 1:
        p.error(f"--repeats {a.repeats}: expected 1 or more")
    if a.repeats > 1 and not a.loop:
        p.error("--repeats repeats the loop's fine-tuning: give --loop")
    import torch

    from s3k.data import Dataset

    torch.set_num_threads(1)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    videos, sleap = recording_files(Path(a.recording))
    keypoints, truth, uv, without, offsets = proofread_points(sleap, Path(a.calibration), a.reference_check)
    ds = Dataset.open(a.data, cache="none")
    splits = dict(zip(ds.column("video_frame").astype(int).tolist(), ds.split_of(ds.frames()).tolist()))
    limbs = skeleton_of(sleap["back"])
    track(Path(a.run), videos, Path(a.calibration), work / "tracked.csv", limbs, a.retrack)
    given = sys.argv[1:] if argv is None else argv
    reference = "proofread labels triangulated from all four cameras"
    if a.reference_check is not None:
        reference = (f"proofread labels within {a.reference_check:g} px of the other cameras' agreement, "
                     "triangulated")
    result: dict = {"command": "python benchmarks/real_tracks.py " + shlex.join(given),
                    "revision": git_revision(), "run": a.run, "units": "mm",
                    "reference": reference,
                    "limbs": limbs, "before": compare(work / "tracked.csv", keypoints, truth, splits)}
    from s3k.experiments.track_filter import jitter

    result["reference_jitter_mm_per_frame2"] = jitter(truth)
    test = np.array([splits.get(f) == "test" for f in range(len(truth))])
    with np.errstate(all="ignore"):  # how far the reference moves on the test frames without one camera
        result["reference_without_one_camera_test_median_mm"] = {
            c: float(np.nanmedian(np.linalg.norm(X[test] - truth[test], axis=-1)))
            for c, X in without.items()}
    if a.reference_check is not None:  # the labels the reference leaves out, on the test frames
        flagged = disagreeing(offsets, a.reference_check)
        result["reference_left_out_test"] = {
            cam: {k: int(n) for k, n in zip(keypoints, mask[test].sum(0)) if n}
            for cam, mask in flagged.items()}
        result["test_points"] = int(np.isfinite(truth[test]).all(-1).sum())
    source = json.loads((work / "tracked.csv.s3k.json").read_text())
    result["filter"] = source.get("filter")
    if a.loop:
        result["loop"] = loop(a, videos, sleap, keypoints, truth, splits, limbs, uv, offsets,
                              result["before"])
    for name in ("raw", "filtered"):
        r = result["before"][name]
        print(f"{name:8s} jitter {r['jitter_mm_per_frame2']:.3f} mm/frame2; test frames median "
              f"{r['test']['median']:.2f} mm, RMS {r['test']['rms']:.2f} mm; all frames median "
              f"{r['all']['median']:.2f} mm")
    if a.loop:
        for what in ("after", "continued_without_new_labels"):
            if what in result["loop"]:
                r = result["loop"][what]["filtered"]["test"]
                print(f"{what}: test frames median {r['median']:.2f} mm, RMS {r['rms']:.2f} mm (filtered)")
    d = result["before"]["filtered_minus_raw_test"]
    lo, hi = d["median_ci95"]
    print(f"filtered - raw, test frames: median {d['median']:+.3f} mm [{lo:+.3f}, {hi:+.3f}], RMS "
          f"{d['rms']:+.3f} mm [{d['rms_ci95'][0]:+.3f}, {d['rms_ci95'][1]:+.3f}]")
    write_and_emit(public(result), a.out)


if __name__ == "__main__":
    main()
