"""Tracking many sessions at once: ``s3k track RUN --manifest FILE`` with 1 worker against 2 on a local Ray
cluster, the wall time of each and their ratio.

The sessions are the real recording's (``../shared/data/real/sleap-anipose-minimal_session``: 4 cameras,
1280 x 1024, 120 frames): each of ``--sessions`` (default 8) names the recording's four videos through links
of its own, so every session decodes its 480 frames and is tracked as one ``s3k track`` tracks it. The
detector is untrained (its weights drawn from a seed; accuracy is not measured here, and the time of a
detector does not depend on its weights): the default U-Net on 128 x 128 inputs cut from the 512 x 512 boxes
of ``scripts/real-recording.sh`` (``--crop``), ``--min-weight 0`` so that the filter runs on every point.

Each count of workers runs the same command line into its own folder (the cluster started and stopped by the
command, as a user runs it), ``--rounds`` times, alternating which count goes first; every folder's files
must be identical. The ratio is of the median wall times. Writes ``--out`` (default
``docs/results/scale/batch-track.json``): the command, the revision, the machine, each run's wall seconds and
per-session table, and the ratio.

Example::

    python benchmarks/batch_track.py --work /tmp/batch-track            # 8 sessions, 1 then 2 workers
    python benchmarks/batch_track.py --sessions 2 --frames 20 --out /tmp/b.json   # a quick look
"""

from __future__ import annotations

import argparse
import filecmp
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, write_and_emit  # noqa: E402
from s3k.detector import MODEL_FILE, DetectorMeta, atomic_save, build_model  # noqa: E402
from s3k.model import UNetConfig  # noqa: E402
from s3k.run_folder import RunFolder  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RECORDING = ROOT.parent / "shared" / "data" / "real" / "sleap-anipose-minimal_session" / "minimal_session"
CAMERAS = ("back", "mid", "side", "top")
CROPS = ("back=610,350,1122,862", "mid=246,374,758,886", "side=328,406,840,918", "top=266,330,778,842")
KEYPOINTS = ("snout", "ear_left", "ear_right", "tail_base")


def make_run(path: Path) -> Path:
    """An untrained detector of the recording's cameras (the default U-Net, 128 x 128 input)."""
    import torch

    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(128, 128), stride=2,
                        sigma=2.0, model=UNetConfig().to_dict(), units="mm", source_image_size=(128, 128))
    torch.manual_seed(0)
    path.mkdir(parents=True)
    RunFolder(path).write_record({}, meta.to_dict(), None)
    atomic_save({"model": build_model(meta).state_dict(), "meta": meta.to_dict()}, path / MODEL_FILE)
    return path


def make_sessions(work: Path, count: int) -> Path:
    """``count`` sessions, each linking the recording's four videos; their manifest."""
    lines = []
    for i in range(count):
        folder = work / "sessions" / f"s{i}"
        folder.mkdir(parents=True)
        for cam in CAMERAS:
            (folder / f"{cam}.mp4").symlink_to(RECORDING / cam / f"minimal_{cam}.mp4")
        lines += ["[[sessions]]", f'session = "s{i}"', f'calibration = "{RECORDING / "calibration.toml"}"',
                  "[sessions.videos]", *(f'{c} = "sessions/s{i}/{c}.mp4"' for c in CAMERAS), ""]
    manifest = work / "sessions.toml"
    manifest.write_text("\n".join(lines))
    return manifest


def track(run: Path, manifest: Path, out: Path, workers: int, frames: int) -> dict:
    """One ``s3k track --manifest`` command: its wall seconds and the lines of its table."""
    cmd = [sys.executable, "-m", "s3k.cli", "track", str(run), "--manifest", str(manifest), "--out", str(out),
           "--workers", str(workers), "--crop", *CROPS, "--min-weight", "0", "--stop", str(frames),
           "--no-progress"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{shlex.join(cmd)} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    table = [line for line in proc.stdout.splitlines() if line.strip()]
    return {"workers": workers, "wall_s": round(wall, 2), "table": table}


def cluster_start_seconds(cpus: int) -> float:
    """The seconds a local Ray cluster takes to start and stop (part of every run's wall time)."""
    import ray

    t0 = time.perf_counter()
    ray.init(num_cpus=cpus, include_dashboard=False, logging_level="WARNING")
    ray.shutdown()
    return round(time.perf_counter() - t0, 2)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sessions", type=int, default=8, help="sessions to track (default 8)")
    p.add_argument("--frames", type=int, default=120, help="frames of each session (default 120, all)")
    p.add_argument("--rounds", type=int, default=2, help="rounds of both counts of workers (default 2)")
    p.add_argument("--work", default="/tmp/batch-track-bench", help="working folder, emptied first")
    p.add_argument("--out", default=str(ROOT / "docs" / "results" / "scale" / "batch-track.json"),
                   help="JSON file to write")
    p.add_argument("--notes", default=None, help="text kept in the JSON")
    args = p.parse_args(argv)
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    run, manifest = make_run(work / "run"), make_sessions(work, args.sessions)
    runs = []
    for r in range(args.rounds):  # 1 then 2 workers, then 2 then 1: a load that drifts weighs on both
        for n in (1, 2) if r % 2 == 0 else (2, 1):
            runs.append({"round": r, **track(run, manifest, work / f"tracks-{n}-{r}", n, args.frames)})
    first = work / "tracks-1-0"
    names = sorted(q.name for q in first.iterdir() if not q.name.startswith("."))
    identical = all(not cmp[1] and not cmp[2] for cmp in (
        filecmp.cmpfiles(first, work / f"tracks-{x['workers']}-{x['round']}", names, shallow=False)
        for x in runs))
    wall = {n: [x["wall_s"] for x in runs if x["workers"] == n] for n in (1, 2)}
    given = sys.argv[1:] if argv is None else argv
    result = {
        "command": shlex.join(["python", "benchmarks/batch_track.py", *given]),
        "revision": git_revision(),
        "sessions": args.sessions, "frames": args.frames, "cameras": len(CAMERAS), "video_size": [1280, 1024],
        "detector": "untrained default U-Net, 128x128 input, 4 keypoints, crops of scripts/real-recording.sh",
        "runs": runs,
        "wall_s": {f"{n}_workers": v for n, v in wall.items()},
        "ratio_1_to_2_workers": round(statistics.median(wall[1]) / statistics.median(wall[2]), 3),
        "ratio_of": "median wall time with 1 worker over the median with 2",
        "cluster_start_stop_s": cluster_start_seconds(2),
        "outputs_identical": identical,
        "load_avg_1min_after": round(os.getloadavg()[0], 2),
        "machine": machine_info(),
    }
    if args.notes:
        result["notes"] = args.notes
    write_and_emit(result, args.out)


if __name__ == "__main__":
    main()
