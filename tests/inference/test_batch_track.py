"""``s3k track RUN --manifest FILE --out FOLDER`` on a local Ray cluster of two workers: each session's files
are those of one ``s3k track``, byte for byte; a worker killed mid-session is retried and leaves nothing
half-written; a rerun skips the finished sessions; a session split into chunks is the whole session's track;
a session that fails does not stop the others. Trainings sent to the cluster (a sweep's jobs,
``run_jobs(..., backend="ray")``) train what they train one after the other on this machine.

The rig is three cameras of 64 x 48 px videos of three coloured dots, the detector a tiny untrained U-Net
(its accuracy is not under test: the files are compared with ``s3k track``'s own)."""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers.tiny_detector import save_run

from s3k import cli
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.rig import Rig
from s3k.data.video import write_video
from s3k.detector import DetectorMeta
from s3k.experiments.accuracy import run_jobs
from s3k.geometry import Cameras, project
from s3k.inference.batch import EXIT_ONCE, plan_chunks, session_files
from s3k.inference.evaluate import evaluate_run
from s3k.inference.track_config import TrackConfig
from s3k.model import UNetConfig

ray = pytest.importorskip("ray")

CAMERAS = ["left", "top", "right"]
KEYPOINTS = ["nose", "ear", "tail"]
W, H = 64, 48
LENGTHS = {"s0": 6, "s1": 7, "s2": 5, "s3": 12}
OPTIONS = ["--min-weight", "0", "--batch", "2", "--no-progress"]


def _rig() -> Rig:
    Rs, ts, Ks = [], [], []
    for c in range(3):
        a = 2 * math.pi * c / 3 + 0.4
        centre = 1000.0 * np.array([math.cos(a), math.sin(a), 0.7]) / math.hypot(1, 0.7)
        z = -centre / np.linalg.norm(centre)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        Rs.append(R)
        ts.append(-R @ centre)
        Ks.append(np.array([[70.0 + 5 * c, 0, (W - 1) / 2], [0, 72.0, (H - 1) / 2], [0, 0, 1]]))
    cams = Cameras.from_numpy(np.stack(Ks), np.zeros((3, 5)), np.stack(Rs), np.stack(ts), dtype=torch.float64)
    return Rig(list(CAMERAS), cams, np.tile(np.array([W, H]), (3, 1)), "mm")


def _videos(folder: Path, rig: Rig, frames: int, phase: float) -> None:
    s = np.arange(frames, dtype=np.float64)[:, None, None] + phase
    base = np.array([[60.0, 0.0, 0.0], [-40.0, 50.0, 10.0], [-30.0, -50.0, 20.0]])
    X = base + np.concatenate([10 * np.sin(0.5 * s), 8 * np.cos(0.3 * s), 5 * s], axis=-1)
    uv, _ = project(rig.cameras[None], torch.as_tensor(X)[:, None])
    folder.mkdir(parents=True)
    for c, name in enumerate(CAMERAS):
        images = []
        for f in range(frames):
            img = np.full((H, W, 3), 80, np.uint8)
            for k, colour in enumerate([(255, 40, 40), (40, 255, 40), (60, 60, 255)]):
                centre = tuple(int(round(float(v) * 4)) for v in uv[f, c, k])
                cv2.circle(img, centre, 10, colour, -1, cv2.LINE_AA, shift=2)
            images.append(img)
        write_video(folder / f"{name}.mp4", images, fps=25)


@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster of two workers, shared by the module (the command joins it)."""
    ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.WARNING)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> dict:
    """Four sessions' videos, their calibration, a manifest of them and a run; each session tracked alone
    by ``s3k track`` into ``serial/<session>.csv``."""
    root = tmp_path_factory.mktemp("batch")
    rig = _rig()
    write_anipose_calibration(root / "calibration.toml", rig)
    lines = []
    for i, (name, frames) in enumerate(LENGTHS.items()):
        _videos(root / name, rig, frames, 3.0 * i)
        lines += ["[[sessions]]", f'session = "{name}"', 'calibration = "calibration.toml"', "test = 2",
                  "[sessions.videos]", *(f'{c} = "{name}/{c}.mp4"' for c in CAMERAS), ""]
    (root / "sessions.toml").write_text("\n".join(lines))
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(32, 32), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="mm", source_image_size=(32, 32))
    run = save_run(root / "run", meta, seed=0)
    for name in LENGTHS:  # the paths as the manifest gives them: relative to its folder
        videos = [f"{c}={root / name / f'{c}.mp4'}" for c in CAMERAS]
        assert cli.main(["track", str(run), "--videos", *videos, "--calibration",
                         str(root / "calibration.toml"), "--out", str(root / "serial" / f"{name}.csv"),
                         *OPTIONS]) == 0
    return {"root": root, "run": run, "manifest": root / "sessions.toml"}


def _batch(sessions: dict, out: Path, *extra: str) -> int:
    return cli.main(["track", str(sessions["run"]), "--manifest", str(sessions["manifest"]), "--out",
                     str(out), "--workers", "2", *OPTIONS, *extra])


def _same_as_serial(sessions: dict, out: Path) -> None:
    files = session_files(Path("x.csv"), TrackConfig())
    for name in LENGTHS:
        for f in files:
            mine, theirs = out / f.name.replace("x.", f"{name}.", 1), sessions["root"] / "serial"
            assert mine.read_bytes() == (theirs / mine.name).read_bytes(), mine.name
    assert not [p.name for p in out.iterdir() if p.name.startswith(".") and p.name != ".s3k-output.json"]


def test_a_batch_writes_each_session_as_track_does_and_a_rerun_skips_them(cluster, sessions, tmp_path,
                                                                         capsys):
    out = tmp_path / "tracks"
    assert _batch(sessions, out) == 0
    _same_as_serial(sessions, out)
    table = capsys.readouterr().out
    assert all(f"{name}" in table for name in LENGTHS) and table.count(" done") == len(LENGTHS)
    stamps = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert _batch(sessions, out) == 0
    assert table.count("\n") == capsys.readouterr().out.count("\n")
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == stamps


def test_a_rerun_says_which_sessions_it_skipped(cluster, sessions, tmp_path, capsys):
    out = tmp_path / "tracks"
    assert _batch(sessions, out) == 0
    (out / "s2.csv.s3k.json").unlink()  # s2 is no longer finished
    capsys.readouterr()
    assert _batch(sessions, out) == 0
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[1:]}
    assert rows["s2"].rstrip().endswith("done")
    assert all("skipped: finished before" in rows[n] for n in LENGTHS if n != "s2")
    _same_as_serial(sessions, out)


def test_a_worker_killed_mid_session_is_retried_and_leaves_every_output_complete(
        cluster, sessions, tmp_path, monkeypatch):
    marks = tmp_path / "marks"
    marks.mkdir()
    for name in ("s0", "s1", "s3"):  # marked as if they had died before: only s2's first attempt dies
        (marks / name).touch()
    monkeypatch.setenv(EXIT_ONCE, str(marks))
    out = tmp_path / "tracks"
    assert _batch(sessions, out) == 0
    assert (marks / "s2").is_file()  # s2's first attempt died after moving its first file into place
    _same_as_serial(sessions, out)


def test_chunks_give_the_whole_session_s_track(cluster, sessions, tmp_path):
    assert plan_chunks(0, 12, 3, 2) == [(0, 4), (4, 8), (8, 12)]
    assert plan_chunks(1, 6, None, 8) == [(1, 6)]
    out = tmp_path / "tracks"
    assert _batch(sessions, out, "--chunk-frames", "3") == 0
    _same_as_serial(sessions, out)


def test_a_failed_session_keeps_the_others_and_fails_the_command(cluster, sessions, tmp_path, capsys):
    manifest = sessions["manifest"].read_text().replace('s1/top.mp4', 's1/missing.mp4')
    (sessions["root"] / "broken.toml").write_text(manifest)
    out = tmp_path / "tracks"
    code = cli.main(["track", str(sessions["run"]), "--manifest", str(sessions["root"] / "broken.toml"),
                     "--out", str(out), *OPTIONS])
    assert code == 1
    text = capsys.readouterr().out
    row = next(line for line in text.splitlines() if line.startswith("s1 "))
    assert "failed: FileNotFoundError" in row and "missing.mp4" in row
    assert not list(out.glob("s1*"))
    assert (out / "s0.csv.s3k.json").is_file() and "1 of 4 sessions failed (s1)" in text


def test_manifest_mistakes_are_one_line(sessions, tmp_path, capsys):
    bad = sessions["root"] / "bad.toml"
    bad.write_text(sessions["manifest"].read_text().replace("test = 2", "tset = 2", 1))
    assert cli.main(["track", str(sessions["run"]), "--manifest", str(bad), "--out",
                     str(tmp_path / "t")]) == 1
    assert "session s0: unknown field 'tset'" in capsys.readouterr().err
    assert cli.main(["track", str(sessions["run"]), "--manifest", str(sessions["manifest"]), "--out",
                     str(tmp_path / "t"), "--calibration", "c.toml"]) == 1
    err = capsys.readouterr().err
    assert "give no --videos or --calibration with --manifest" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "t").exists()
    assert cli.main(["track", str(sessions["run"]), "--videos", "a=a.mp4", "b=b.mp4", "--calibration",
                     "c.toml", "--out", str(tmp_path / "t.csv"), "--chunk-frames", "10"]) == 1
    assert "--chunk-frames applies to --manifest only" in capsys.readouterr().err


def _trainings(data: Path, work: Path) -> list[tuple[str, list[str], Path]]:
    work.mkdir()
    return [(f"seed {seed}", [sys.executable, "-m", "s3k.cli", "train", str(data), "--out",
                              str(work / f"r{seed}"), "--steps", "2", "--seed", str(seed), "--channels",
                              "8,16", "--res-blocks", "1", "--batch-labelled", "2", "--batch-unlabelled", "2",
                              "--warmup-steps", "0", "--ramp-steps", "1", "--no-progress"],
              work / f"r{seed}-cpu.json")
            for seed in (0, 1)]


def test_a_sweep_on_ray_trains_what_the_local_sweep_trains(cluster, tiny_dataset, tmp_path):
    serial, on_ray = _trainings(tiny_dataset, tmp_path / "serial"), _trainings(tiny_dataset, tmp_path / "ray")
    run_jobs(serial, parallel=1, poll_s=0.2)
    run_jobs(on_ray, parallel=2, backend="ray")
    for (_, a, record_a), (_, b, record_b) in zip(serial, on_ray):
        run_a, run_b = Path(a[a.index("--out") + 1]), Path(b[b.index("--out") + 1])
        weights_a = torch.load(run_a / "model.pt", weights_only=False)["model"]
        weights_b = torch.load(run_b / "model.pt", weights_only=False)["model"]
        assert weights_a.keys() == weights_b.keys()
        assert all(torch.equal(weights_a[k], weights_b[k]) for k in weights_a)
        metrics = [evaluate_run(r, tiny_dataset, split="test", device="cpu") for r in (run_a, run_b)]
        assert json.dumps(metrics[0], sort_keys=True) == json.dumps(metrics[1], sort_keys=True)
        records = [json.loads(r.read_text()) for r in (record_a, record_b)]
        assert records[0].keys() == records[1].keys() == {"cpu_minutes", "wall_minutes"}  # timings only
        assert records[1]["cpu_minutes"] > 0
