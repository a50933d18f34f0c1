"""``s3k track RUN --manifest FILE --out FOLDER``: many sessions tracked at once, as tasks on a Ray cluster.

Each session is what one ``s3k track`` makes of it (:func:`s3k.inference.track.track`): the same files, byte
for byte, under ``FOLDER`` (``<session>.csv`` and its companions, or the manifest's ``out``). Sessions are
independent, so they run side by side, one torch thread each, as many at once as the cluster has CPUs
(``workers`` bounds it). Ray is a local cluster started in this process (``ray.init``, no server), or one that
is running (``address``, or the ``RAY_ADDRESS`` environment variable); every node must see the run, the
videos and ``FOLDER`` at the same paths.

- **Nothing half-written.** A task writes its session's files into a hidden folder beside them
  (``.<csv>.tracking``), then moves them into place one by one, the CSV's JSON companion (``<csv>.s3k.json``)
  last: a session is finished when its companion is there, with every other file of it. A worker killed
  at any moment leaves the session unfinished; Ray runs the task again (``max_retries``), which clears what
  the killed attempt left and writes the whole session.
- **Reruns.** A finished session of the same run, videos, calibration and filter is skipped; one of other
  inputs is refused unless ``overwrite``. A session that fails (a bad video, a calibration that does not
  fit) is reported with its reason; the other sessions' files are kept.
- **Chunks.** With ``chunk_frames``, a session's frames are detected in parts on several workers (each
  frame's detection is its own, so the raw points are those of one worker); the parts are joined and the
  filter runs over the whole track, as one ``s3k track`` filters it: its noise is fitted by likelihood over
  the whole track and its layout and limb references are the track's medians
  (:mod:`s3k.inference.track_filter`), so filtering parts apart would change the points.
"""

from __future__ import annotations

import csv
import logging
import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from s3k.base.errors import UserError
from s3k.base.outputs import check_folder, check_output, claim_folder
from s3k.data import video
from s3k.data.rig import check_camera_name
from s3k.data.tracks_csv import read_source, source_path
from s3k.detector import Detector
from s3k.inference.session import RigOptions, RigSession
from s3k.inference.track import (
    Track,
    assemble_track,
    detect_frames,
    detect_videos,
    frame_range,
    join_frames,
    video_sizes,
)
from s3k.inference.track_config import TrackConfig
from s3k.inference.track_filter import doubt_path, raw_path

log = logging.getLogger(__name__)

__all__ = ["KIND", "RETRIES", "BatchSession", "SessionResult", "connect_ray", "plan_chunks", "session_files",
           "table", "track_batch"]

KIND = "folder of tracks"
"""The kind of output ``FOLDER`` is marked as (:func:`s3k.base.outputs.claim_folder`)."""
RETRIES = 3
"""How many times a session's task runs again after its worker died (Ray's ``max_retries``)."""
EXIT_ONCE = "S3K_BATCH_EXIT_ONCE"
"""For the tests: a folder; a session's first attempt exits after moving its first file into place (and
leaves a mark there, so the retry goes through)."""


@dataclass(frozen=True)
class BatchSession:
    """One session: ``name``, its ``videos`` (``{camera: path}``), its rig and the CSV it writes (``out``)."""

    name: str
    videos: dict[str, Path]
    rig: RigOptions
    out: Path


@dataclass
class SessionResult:
    """What became of a session: ``status`` ``done``, ``skipped`` or ``failed`` (``reason``, one line),
    its ``frames``, the share of its keypoints' frames with a 3D point (``valid``) and the task's
    ``seconds``."""

    session: str
    status: str
    frames: int | None = None
    seconds: float = 0.0
    valid: float | None = None
    reason: str = ""


def session_files(out: Path, config: TrackConfig) -> list[Path]:
    """The files a session's CSV ``out`` comes with, in the order they are moved into place (the CSV's
    companion, which says the session is finished, last)."""
    files = [raw_path(out), source_path(raw_path(out))] if config.filtering_on else []
    return [*files, doubt_path(out), out, source_path(out)]


def plan_chunks(start: int, end: int, chunk_frames: int | None, batch: int) -> list[tuple[int, int]]:
    """The parts ``(a, b)`` of the instants ``start .. end - 1``, ``chunk_frames`` rounded up to a multiple
    of ``batch`` (so every part's batches are the ones the whole range reads); one part without a size."""
    if not chunk_frames:
        return [(start, end)]
    size = -(-chunk_frames // batch) * batch
    return [(a, min(a + size, end)) for a in range(start, end, size)]


def _stage(s: BatchSession) -> Path:
    return s.out.parent / f".{s.out.name}.tracking"


def _inputs(s: BatchSession) -> dict[str, object]:
    return {"--calibration": s.rig.calibration, "--videos": list(s.videos.values())}


def _finished(s: BatchSession, run: str, config: TrackConfig) -> str | None:
    """None when ``s`` is not finished; ``""`` when it is, of these inputs; else why it is another's."""
    if not all(p.is_file() for p in session_files(s.out, config)):
        return None
    try:
        record = read_source(s.out) or {}
    except UserError as exc:
        return str(exc)
    filtered = (record.get("filter") or {}).get("settings")
    wanted = config.filter_settings().to_dict() if config.filtering_on else None
    for what, have, want in (("run", record.get("run"), run), ("calibration", record.get("calibration"),
                                                              str(s.rig.calibration)),
                             ("videos", record.get("videos"), {c: str(p) for c, p in s.videos.items()}),
                             ("filter", filtered, wanted)):
        if have != want:
            return f"{s.out} is a track of another {what} ({have})"
    return ""


def _valid_share(csv_path: Path) -> tuple[int, float | None]:
    """Frames and the share of points that are not ``nan`` in a track's CSV."""
    with open(csv_path, newline="") as fh:
        rows = list(csv.reader(fh))
    cols = [i for i, name in enumerate(rows[0]) if name.endswith("_x")] if rows else []
    cells = [r[i] for r in rows[1:] for i in cols]
    return len(rows) - 1, (sum(c not in ("", "nan") for c in cells) / len(cells)) if cells else None


def _check(run: str, sessions: Sequence[BatchSession], folder: Path, config: TrackConfig,
           overwrite: bool) -> dict[str, SessionResult]:
    """Refuse what a batch may not write, before any work; the sessions already finished (skipped, or
    refused as another's)."""
    if config.outputs.overlay:
        raise UserError(f"--overlay {config.outputs.overlay}: overlay videos are made one session at a time",
                        hint="track the session alone (without --manifest) to draw its overlays")
    names = [s.name for s in sessions]
    twice = sorted({n for n in names if names.count(n) > 1}) or sorted(
        {str(s.out) for s in sessions if [t.out for t in sessions].count(s.out) > 1})
    if twice:
        raise UserError(f"--manifest: {twice[0]!r} is given to two sessions", hint="give each its own name "
                        "and out")
    check_folder(folder, KIND, inputs={f"session {s.name}": list(s.videos.values()) for s in sessions})
    results = {}
    for s in sessions:
        check_camera_name(s.name, f"--manifest session {s.name!r}")
        if not s.out.resolve().is_relative_to(folder.resolve()):
            raise UserError(f"--manifest session {s.name}: out {s.out} is outside --out {folder}")
        for path in session_files(s.out, config):
            check_output(path, True, inputs=_inputs(s))
        state = _finished(s, run, config)
        if state == "" and not overwrite:
            frames, valid = _valid_share(raw_path(s.out) if config.filtering_on else s.out)
            results[s.name] = SessionResult(s.name, "skipped", frames, 0.0, valid, "finished before")
        elif state and not overwrite:
            results[s.name] = SessionResult(s.name, "failed",
                                            reason=f"{state}; pass --overwrite to replace it")
    return results


def track_batch(run: str | Path, sessions: Sequence[BatchSession], folder: str | Path,
                config: TrackConfig | None = None, *, workers: int | None = None, address: str | None = None,
                chunk_frames: int | None = None, overwrite: bool = False,
                progress: bool = True) -> list[SessionResult]:
    """Track every session (module docstring) into ``folder``; one :class:`SessionResult` per session, in
    their order.

    Args:
        run: the run folder (each task loads it).
        sessions: the sessions, their CSVs inside ``folder``.
        folder: where the tracks go: new, empty, or made by an earlier batch.
        config: the settings of every session (``s3k track``'s).
        workers: sessions (or chunks) at once (default: the cluster's CPUs).
        address: a running Ray cluster to join (default: ``RAY_ADDRESS``, else a local one of ``workers``
            CPUs, or this machine's).
        chunk_frames: split each session into parts of this many frames (default: whole sessions).
        overwrite: track again the sessions already finished.
        progress: show a bar over the sessions.
    """
    config = (config or TrackConfig()).validate()
    run, folder = str(run), Path(folder)
    results = _check(run, sessions, folder, config, overwrite)
    claim_folder(folder, KIND)
    todo = [s for s in sessions if s.name not in results]
    if todo:  # the bar is over the sessions, none in the tasks
        results.update(_on_ray(run, todo, config.replace(progress=False), workers, address, chunk_frames,
                               progress))
    for s in sessions:
        shutil.rmtree(_stage(s), ignore_errors=True)  # a session that failed for good leaves nothing
    return [results[s.name] for s in sessions]


def connect_ray(workers: int | None, address: str | None) -> bool:
    """Join the Ray cluster at ``address`` (or ``RAY_ADDRESS``), or start a local one of ``workers`` CPUs
    (default: this machine's); True when started here. A cluster this process already joined is used as it
    is."""
    import ray

    if ray.is_initialized():
        return False
    address = address or os.environ.get("RAY_ADDRESS") or None
    quiet: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": True}
    if address:
        try:
            ray.init(address=address, **quiet)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise UserError(f"--address {address}: cannot join the Ray cluster ({str(exc).splitlines()[0]})",
                            hint="start it with 'ray start --head', or leave out --address and RAY_ADDRESS "
                                 "for a local one") from None
    else:
        ray.init(num_cpus=workers or os.cpu_count() or 1, include_dashboard=False, **quiet)
    return True


def _reason(exc: BaseException) -> str:
    """One line of what went wrong (a task's own error, not Ray's wrapping of it)."""
    cause = getattr(exc, "cause", None) or exc
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[0] if text else ''}"


def _on_ray(run: str, todo: list[BatchSession], config: TrackConfig, workers: int | None,
            address: str | None, chunk_frames: int | None, progress: bool) -> dict[str, SessionResult]:
    """The sessions ``todo`` as Ray tasks, at most ``workers`` at once."""
    import ray

    started = connect_ray(workers, address)
    try:
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        limit = min(workers or cpus, cpus)
        task = {"whole": ray.remote(num_cpus=1, max_retries=RETRIES)(_track_whole),
                "chunk": ray.remote(num_cpus=1, max_retries=RETRIES)(_detect_chunk),
                "finish": ray.remote(num_cpus=1, max_retries=RETRIES)(_finish_chunks)}
        hook = os.environ.get(EXIT_ONCE)
        queue: list[tuple[str, BatchSession, tuple]] = []
        for s in todo:
            if chunk_frames:
                offsets = [int((s.rig.frame_offsets or {}).get(c, 0)) for c in s.videos]
                parts = plan_chunks(*frame_range(s.videos, offsets, config), chunk_frames,
                                    config.chunks.batch)
                queue += [("chunk", s, part) for part in parts]
            else:
                queue.append(("whole", s, ()))
        return _drive(ray, task, queue, run, config, hook, limit, progress, len(todo))
    finally:
        if started:
            ray.shutdown()


def _drive(ray, task: dict, queue: list, run: str, config: TrackConfig, hook: str | None, limit: int,
           progress: bool, total: int) -> dict[str, SessionResult]:
    """Submit the queue's tasks, ``limit`` at once; a session's chunks done, its finishing task."""
    results: dict[str, SessionResult] = {}
    running: dict[Any, tuple[str, BatchSession]] = {}
    chunks: dict[str, list] = {}
    left = {s.name: sum(1 for _, t, _ in queue if t.name == s.name) for _, s, _ in queue}
    began: dict[str, float] = {}
    bar = tqdm(total=total, unit="session", desc="sessions", disable=not progress)
    while queue or running:
        while queue and len(running) < limit:
            kind, s, extra = queue.pop(0)
            began.setdefault(s.name, time.perf_counter())
            if kind == "finish":
                ref = task[kind].remote(run, s, config, hook, *chunks.pop(s.name))
            else:
                ref = task[kind].remote(run, s, config, hook, *extra)
            running[ref] = (kind, s)
            if kind == "chunk":
                chunks.setdefault(s.name, []).append(ref)
        ready, _ = ray.wait(list(running), num_returns=1)
        kind, s = running.pop(ready[0])
        if s.name in results:  # a chunk of a session that already failed
            continue
        try:
            got = ray.get(ready[0])
        except Exception as exc:  # the task's error, or its worker died RETRIES + 1 times
            got = SessionResult(s.name, "failed", reason=_reason(exc))
        if kind == "chunk":
            left[s.name] -= 1
            if left[s.name] == 0:
                queue.insert(0, ("finish", s, ()))
            if not isinstance(got, SessionResult):
                continue
        got.seconds = time.perf_counter() - began[s.name]
        results[s.name] = got
        queue = [q for q in queue if q[1].name != s.name]
        bar.update(1)
    bar.close()
    return results


def _place(run: str, s: BatchSession) -> RigSession:
    """The run's detector on the session's rig, in a task of one CPU: one torch thread, one decoding
    thread per video."""
    torch.set_num_threads(1)
    video.decode_threads(1)
    detector = Detector.load(run, s.rig.device)
    return RigSession.place(detector, video_sizes(s.videos), s.rig, "--videos", s.videos, level=logging.DEBUG)


def _track_whole(run: str, s: BatchSession, config: TrackConfig, hook: str | None) -> SessionResult:
    """A Ray task: the whole session tracked and written in place."""
    try:
        result = detect_videos(_place(run, s), s.videos, config)
        return _write_in_place(result, s, hook)
    except Exception as exc:  # reported in the session's line; the other sessions go on
        return SessionResult(s.name, "failed", reason=_reason(exc))


def _detect_chunk(run: str, s: BatchSession, config: TrackConfig, hook: str | None, start: int, end: int):
    """A Ray task: the read-out of the instants ``start .. end - 1`` of the session."""
    return detect_frames(_place(run, s), s.videos, config, start, end)


def _finish_chunks(run: str, s: BatchSession, config: TrackConfig, hook: str | None, *parts) -> SessionResult:
    """A Ray task: the session's parts joined, filtered over the whole track and written in place."""
    try:
        result = assemble_track(_place(run, s), s.videos, config, join_frames(list(parts)))
        return _write_in_place(result, s, hook)
    except Exception as exc:
        return SessionResult(s.name, "failed", reason=_reason(exc))


def _write_in_place(result: Track, s: BatchSession, hook: str | None) -> SessionResult:
    """Write the session's files into its hidden folder, then move them into place, the CSV's companion
    last (module docstring)."""
    stage = _stage(s)
    shutil.rmtree(stage, ignore_errors=True)  # what a killed attempt left
    stage.mkdir(parents=True)
    try:
        written = {p.name: p for p in result.write(stage / s.out.name, calibration=s.rig.calibration)}
        source_path(s.out).unlink(missing_ok=True)  # unfinished until every file is in place
        for i, path in enumerate(session_files(s.out, result.config)):
            os.replace(written[path.name], path)
            if i == 0 and hook:
                _exit_once(Path(hook), s.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    valid = float(np.mean(result.raw.valid)) if result.frames else None
    return SessionResult(s.name, "done", result.frames, 0.0, valid)


def _exit_once(folder: Path, name: str) -> None:
    """The tests' killed worker (:data:`EXIT_ONCE`): the first attempt of a session dies here."""
    mark = folder / name
    if not mark.exists():
        mark.touch()
        os._exit(1)


def table(results: Sequence[SessionResult]) -> list[str]:
    """The lines of the per-session table."""
    lines = [f"{'session':<20} {'frames':>7} {'seconds':>8} {'valid':>6}  status"]
    for r in results:
        frames = "-" if r.frames is None else str(r.frames)
        valid = "-" if r.valid is None else f"{100 * r.valid:.0f}%"
        status = r.status + (f": {r.reason}" if r.reason else "")
        lines.append(f"{r.session:<20} {frames:>7} {r.seconds:>8.1f} {valid:>6}  {status}")
    return lines
