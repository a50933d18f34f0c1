"""``s3k track`` and :func:`s3k.track`: 3D keypoints from synchronized videos of a calibrated rig, written in
anipose's CSV layout.

Pipeline, per frame (the same read-out as training, ``s3k predict`` and ``s3k evaluate``):

1. The C videos are decoded in lockstep (:func:`s3k.data.video.synchronized_frames`): frame ``i`` of every
   video is one instant (anipose's assumption for a synchronized rig), or, for cameras whose clocks are off
   (``--frame-offsets CAM=N``, estimated by ``s3k validate``), instant ``i`` is frame ``i - N`` of the camera.
2. A :class:`s3k.inference.session.RigSession` (the detector placed on the rig) maps each image onto the
   detector's input through its camera's box (the ``--crop`` given, the box the run was trained on, or
   ``--fit``).
3. The detector's read-out gives the detections in the original video pixels, their confidence weights and
   the confidence-weighted triangulation of the views above ``min_weight`` in the calibration's own cameras
   (lens distortion included), so the 3D points are in the calibration's world frame and units.
4. The points are filtered over time (:mod:`s3k.inference.track_filter`) unless ``filter="none"``.

:class:`Track` holds the result and writes every file of it (:meth:`Track.write`): the CSV of
:mod:`s3k.data.tracks_csv` (``error`` in pixels of the original video, ``fnum`` the video frame index), the
raw points in ``<stem>.raw.csv`` when filtered, the frames ranked by doubt in ``<stem>.doubt.csv``, each
CSV's JSON companion (its units, run, calibration, videos and filter) and, with ``overlay``, one MP4 per
camera (``DIR/<camera>.mp4``) that shows, on the original frames, the reprojected 3D keypoints (filled
discs) and the per-view detections (crosses), one colour per keypoint (:func:`s3k.base.draw.draw_overlay`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from s3k.base.draw import draw_overlay, edge_indices, keypoint_colours
from s3k.base.errors import UserError
from s3k.base.outputs import check_folder, check_output, claim_folder
from s3k.data import imageseq, video
from s3k.data.rig import check_camera_name
from s3k.data.tracks_csv import array_rows, write_csv, write_source
from s3k.detector import Detector
from s3k.inference.kalman import Smoothed
from s3k.inference.session import RigOptions, RigSession
from s3k.inference.track_config import TrackConfig
from s3k.inference.track_filter import (
    check_rigid,
    doubt,
    doubt_path,
    filter_track,
    layout_shape_of,
    raw_path,
    write_doubt,
)

log = logging.getLogger(__name__)

__all__ = ["Track", "assemble_track", "detect_frames", "detect_videos", "empty_result_hint", "frame_range",
           "join_frames", "keypoint_line", "limb_indices", "overlay_file", "track", "video_sizes"]

OVERLAYS = "folder of overlay videos"


def track(run: str | Path | Detector, videos: Mapping[str, str | Path], rig: RigOptions | str | Path,
          out: str | Path, config: TrackConfig | None = None, overwrite: bool = False) -> Track:
    """What ``s3k track`` does: check every output, load the run's detector (or take the one given), place
    it on the rig, track the videos and write every file (:meth:`Track.write`).

    Args:
        run: a run folder of ``s3k train`` (one pass or two), or a loaded :class:`s3k.detector.Detector`.
        videos: ``{camera: video or image sequence}``, at least two, in the order of the outputs.
        rig: the calibration file, or the :class:`s3k.inference.session.RigOptions` of the rig.
        out: the CSV to write.
        config: the :class:`s3k.inference.track_config.TrackConfig` (default: ``s3k track``'s defaults).
        overwrite: replace existing outputs.
    """
    config = (config or TrackConfig()).validate()
    rig = rig if isinstance(rig, RigOptions) else RigOptions(rig)
    paths = {c: Path(p) for c, p in videos.items()}
    _check_files(out, overwrite, config, list(paths),
                 {"--calibration": rig.calibration, "--videos": list(paths.values())})
    sizes = video_sizes(paths)
    detector = run if isinstance(run, Detector) else Detector.load(run, rig.device)
    session = RigSession.place(detector, sizes, rig, "--videos", paths)
    result = detect_videos(session, paths, config)
    result.write(out, overwrite, calibration=rig.calibration)
    return result


def _check_files(out: str | Path, overwrite: bool, config: TrackConfig, cameras: list[str],
                 inputs: dict[str, object]) -> None:
    """Refuse, before any work, an output :meth:`Track.write` would refuse (:mod:`s3k.base.outputs`)."""
    overlay = config.outputs.overlay
    overlays = {overlay_file(overlay, c).name for c in cameras} if overlay else set()
    for path in (out, raw_path(out), doubt_path(out)) if config.filtering_on else (out, doubt_path(out)):
        check_output(path, overwrite, inputs=inputs)
    if config.outputs.overlay:
        check_folder(config.outputs.overlay, OVERLAYS, option="--overlay", inputs=inputs, writes=overlays)


def overlay_file(folder: str | Path, camera: str) -> Path:
    """The overlay video of ``camera`` in ``folder`` (``folder/<camera>.mp4``), refused (one line) unless it
    lies in ``folder`` itself: a camera's name never leads the file elsewhere."""
    check_camera_name(camera, "--overlay")
    path = Path(folder) / f"{camera}.mp4"
    if path.resolve().parent != Path(folder).resolve():
        raise UserError(f"--overlay {folder}: camera {camera!r} would write its video outside the folder "
                        f"({path})", hint="rename the camera")
    return path


def video_sizes(videos: dict[str, Path]) -> dict[str, tuple[int, int]]:
    """``{camera: (W, H)}`` of each video or image sequence.

    Raises:
        FileNotFoundError: naming the camera and the missing file.
    """
    sizes = {}
    for name, path in videos.items():
        if not video.exists(path):
            raise FileNotFoundError(f"--videos {name}={path}: no such video file, image folder or image "
                                    "pattern")
        sizes[name] = video.frame_size(path)
    return sizes


@dataclass
class _Collected:
    """What :func:`detect_videos` keeps of every frame: ``fnums (T,)``, ``X (T, K, 3)``, ``error``, ``ncams``,
    ``score``, ``valid`` ``(T, K)``, ``used``, ``weights``, ``residual`` ``(T, C, K)``, ``reproj``, ``uv``
    ``(T, C, K, 2)``."""

    fnums: np.ndarray
    X: np.ndarray
    error: np.ndarray
    ncams: np.ndarray
    score: np.ndarray
    valid: np.ndarray
    used: np.ndarray
    weights: np.ndarray
    residual: np.ndarray
    reproj: np.ndarray
    uv: np.ndarray


def detect_videos(session: RigSession, videos: dict[str, Path], config: TrackConfig | None = None) -> Track:
    """Track the synchronized ``videos`` (``{camera: path}`` in the session's camera order) with the
    session's detector: every frame's read-out, then the filter over time; nothing is written."""
    config = (config or TrackConfig()).validate()
    if config.filtering_on:  # before any frame is read
        check_rigid(config.filter_settings(), layout_shape_of(session.detector.meta.layout),
                    f"the run {session.detector.run}")
    start, end = frame_range(_session_paths(session, videos), session.offsets, config)
    return assemble_track(session, videos, config, detect_frames(session, videos, config, start, end))


def _session_paths(session: RigSession, videos: Mapping[str, str | Path]) -> dict[str, Path]:
    return {name: Path(videos[name]) for name in session.names}


def frame_range(videos: Mapping[str, Path], offsets: list[int] | None,
                config: TrackConfig) -> tuple[int, int]:
    """The instants ``start .. end - 1`` that ``config`` tracks of ``videos`` (``{camera: path}``, cameras
    with ``offsets``, :attr:`s3k.inference.session.RigSession.offsets`)."""
    paths = list(videos.values())
    rates = [video.frame_rate(p) for p in paths]
    return _frame_range(list(videos), paths, rates, config.chunks.start, config.chunks.stop,
                        offsets or [0] * len(paths))


def detect_frames(session: RigSession, videos: Mapping[str, str | Path], config: TrackConfig, start: int,
                  end: int) -> _Collected:
    """The read-out of the instants ``start .. end - 1`` (:func:`frame_range`): each frame's alone, so any
    split of a range into parts gives, joined (:func:`join_frames`), what the whole range gives."""
    paths = list(_session_paths(session, videos).values())
    offsets = session.offsets or [0] * len(paths)
    frames = video.prefetch(video.synchronized_batches(paths, config.chunks.batch, start, end, offsets))
    return _detect(session, frames, config.readout.min_weight, end - start, config.outputs.progress)


def join_frames(parts: list[_Collected]) -> _Collected:
    """Consecutive ranges' read-outs (:func:`detect_frames`) as one."""
    return _Collected(**{name: np.concatenate([getattr(p, name) for p in parts])
                         for name in _Collected.__dataclass_fields__})


def assemble_track(session: RigSession, videos: Mapping[str, str | Path], config: TrackConfig,
                   got: _Collected) -> Track:
    """The :class:`Track` of the read-outs ``got`` of ``videos``, filtered over time as ``config`` says."""
    settings, limbs = config.filter_settings(), config.limb_pairs()
    detector = session.detector
    shape = layout_shape_of(detector.meta.layout)
    if config.filtering_on:
        check_rigid(settings, shape, f"the run {detector.run}")
    paths = _session_paths(session, videos)
    rates = [video.frame_rate(p) for p in paths.values()]
    rate = None if any(imageseq.is_sequence(p) for p in paths.values()) else _common_rate(rates)
    result = Track(session, paths, config, got, rate)
    if config.filtering_on:
        limbs = detector.meta.recorded_skeleton() if limbs is None else limbs
        edges = limb_indices(limbs, detector.keypoints)
        assert session.cameras is not None
        result.filtered = filter_track(got.X, got.error, got.score, got.used.astype(bool),
                                       session.cameras.numpy(), settings, shape, edges)
    return result


def _stack_views(frames: list[list[np.ndarray]]) -> np.ndarray | list[np.ndarray]:
    """``B`` frames of ``C`` images -> one array ``(B, C, H, W, 3)`` when the cameras' sizes agree, else ``C``
    arrays ``(B, H_c, W_c, 3)`` (:class:`s3k.detector.Detector`)."""
    if len({f.shape for frame in frames for f in frame}) == 1:
        return np.stack([np.stack(frame) for frame in frames])
    return [np.stack([f[c] for f in frames]) for c in range(len(frames[0]))]


def _frame_range(names: list[str], paths: list[Path], rates: list[float], start: int,
                 stop: int | None, offsets: list[int]) -> tuple[int, int]:
    """The instants ``start .. end - 1`` to track (camera ``c`` films instant ``i`` as its frame
    ``i - offsets[c]``); warns about videos of different lengths or frame rates."""
    counts = {name: video.frame_count(p) for name, p in zip(names, paths)}
    first, n_video = max(0, *offsets), min(counts[n] + k for n, k in zip(names, offsets))
    shifted = f" with --frame-offsets {dict(zip(names, offsets))}" if any(offsets) else ""
    lengths = ", ".join(f"{k}: {v}" for k, v in counts.items())
    if n_video <= first:
        raise UserError(f"--frame-offsets {dict(zip(names, offsets))}: no instant is filmed by every camera "
                        f"(frames: {lengths})")
    if len(set(counts.values())) > 1 or any(offsets):
        log.warning(f"the videos have {lengths} frames{shifted}; tracking the instants {first} to "
                    f"{n_video - 1}, which every camera filmed")
    if max(rates) - min(rates) > 1e-3 * max(rates):
        log.warning(f"the videos have different frame rates ({dict(zip(names, rates))}); frames are paired "
                    "by index")
    if start >= n_video:
        raise UserError(f"--start {start}: the videos have {n_video} frames{shifted}")
    return max(start, first), n_video if stop is None else min(stop, n_video)


def _common_rate(rates: list[float]) -> float | None:
    """The frame rate every video declares (None where they differ)."""
    rates = [float(r) for r in rates]
    return rates[0] if rates and max(rates) - min(rates) <= 1e-3 * max(rates) else None


def _detect(session: RigSession, frames, min_weight: float, total: int, progress: bool) -> _Collected:
    """Detect every batch of ``frames``; the :class:`_Collected` arrays."""
    detector, cams, boxes = session.detector, session.cameras, session.boxes
    assert cams is not None
    names = list(_Collected.__dataclass_fields__)
    parts: dict[str, list[np.ndarray]] = {name: [] for name in names}
    bar = tqdm(total=total, unit="frame", disable=not progress, desc="track")
    for fnums, originals in frames:
        result = detector(_stack_views(originals), cams, boxes, min_weight).cpu()
        parts["fnums"].append(np.asarray(fnums))
        for name in names[1:]:
            parts[name].append(np.asarray(getattr(result, name)))
        bar.update(len(fnums))
    bar.close()
    K, C = len(detector.keypoints), len(session.names)
    empty = {"fnums": (0,), "X": (0, K, 3), "used": (0, C, K), "weights": (0, C, K), "residual": (0, C, K),
             "reproj": (0, C, K, 2), "uv": (0, C, K, 2)}
    return _Collected(**{name: np.concatenate(v) if v else np.zeros(empty.get(name, (0, K)))
                         for name, v in parts.items()})


def limb_indices(skeleton, keypoints: list[str]) -> list[tuple[int, int]]:
    """The skeleton's limbs (pairs of names) as keypoint index pairs; a name the run does not have is
    refused."""
    out = []
    for a, b in skeleton:
        for name in (a, b):
            if name not in keypoints:
                raise UserError(f"--filter-limbs: keypoint {name!r} is not one of the run's "
                                f"({', '.join(keypoints)})")
        out.append((keypoints.index(a), keypoints.index(b)))
    return out


@dataclass
class Track:
    """The 3D points of a recording (:func:`detect_videos`) and everything they were made from.

    Attributes:
        session: the detector on the rig.
        videos: ``{camera: path}`` in the session's camera order.
        config: the settings.
        raw: every frame's read-out (``fnums``, ``X``, ``error``, ``ncams``, ``score``, ``valid``, ``used``,
            ``weights``, ``residual``, ``reproj``, ``uv``).
        fps: the videos' frame rate (None where they differ or an image sequence records none).
        filtered: the filter's result (:class:`s3k.inference.kalman.Smoothed`), or None.
    """

    session: RigSession
    videos: dict[str, Path]
    config: TrackConfig
    raw: _Collected
    fps: float | None = None
    filtered: Smoothed | None = None
    files: list[Path] = field(default_factory=list)

    @property
    def keypoints(self) -> list[str]:
        return list(self.session.detector.keypoints)

    @property
    def frames(self) -> int:
        return len(self.raw.fnums)

    @property
    def points(self) -> np.ndarray:
        """``(T, K, 3)`` the points written to the CSV: filtered when a filter ran, else raw."""
        return self.raw.X if self.filtered is None else self.filtered.X

    @property
    def filter_record(self) -> dict | None:
        """The filter's settings and what it fitted and did (the CSV's companion's ``filter``), or None."""
        if self.filtered is None:
            return None
        return {"settings": self.config.filter_settings().to_dict(), **self.filtered.info}

    def fractions(self) -> tuple[list[float], list[float], list[float]]:
        """Per keypoint: the fraction of frames with a 3D point, the median reprojection error (video
        pixels) and the fraction of frames with at least two views above ``min_weight``."""
        valid, err, ok = self.raw.valid.astype(bool), self.raw.error, self.raw.ncams >= 2
        K = len(self.keypoints)
        med = [float(np.median(err[valid[:, k], k])) if valid[:, k].any() else float("nan") for k in range(K)]
        frac = [float(valid[:, k].mean()) if len(valid) else 0.0 for k in range(K)]
        pas = [float(ok[:, k].mean()) if len(ok) else 0.0 for k in range(K)]
        return frac, med, pas

    def write(self, out: str | Path, overwrite: bool = False,
              calibration: str | Path | None = None) -> list[Path]:
        """Write every file (module docstring) and log what was written; returns the files.

        Args:
            out: the CSV.
            overwrite: replace existing files.
            calibration: the calibration file, for the JSON companions.
        """
        inputs: dict[str, object] = {"--calibration": calibration, "--videos": list(self.videos.values())}
        _check_files(out, overwrite, self.config, list(self.videos),
                     {k: v for k, v in inputs.items() if v is not None})
        out, raw = Path(out), raw_path(out) if self.filtered is not None else Path(out)
        files = self._write_overlays(Path(self.config.outputs.overlay)) if self.config.outputs.overlay else []
        rejected = None if self.filtered is None else self.filtered.rejected
        keypoints, got = self.keypoints, self.raw
        with write_csv(raw, keypoints) as writer:
            writer.writerows(array_rows(got.fnums.tolist(), got.X, got.error, got.ncams, got.score))
        if self.filtered is not None:
            with write_csv(out, keypoints) as writer:
                ncams = np.where(self.filtered.measured, got.ncams, 0)  # 0: no measurement entered the filter
                writer.writerows(array_rows(got.fnums.tolist(), self.filtered.X, got.error, ncams, got.score))
        doubts = doubt(got.weights, got.residual, got.valid.astype(bool), rejected)
        ranked = write_doubt(doubt_path(out), got.fnums.tolist(), doubts, keypoints, rejected)
        files += self._write_sources(out, raw, ranked, calibration)
        self.files = [*files, raw, out, ranked] if self.filtered is not None else [*files, out, ranked]
        for line in self.report(out, raw, ranked):
            (log.warning if line.startswith("warning: ") else log.info)(line.removeprefix("warning: "))
        return self.files

    def _write_sources(self, out: Path, raw: Path, ranked: Path, calibration) -> list[Path]:
        """The JSON companions of the CSVs (:func:`s3k.data.tracks_csv.write_source`)."""
        details = {"videos": {c: str(p) for c, p in self.videos.items()}, "start": self.config.chunks.start,
                   "doubt": ranked.name}
        if any(self.session.offsets):
            details["frame_offsets"] = dict(zip(self.session.names, self.session.offsets))
        source = {"run": self.session.detector.run, "calibration": calibration, "fps": self.fps}
        files = []
        if self.filtered is not None:
            files.append(write_source(raw, self.session.units, details, **source))
            details.update(raw=raw.name, filter=self.filter_record)
        files.append(write_source(out, self.session.units, details, **source))
        return files

    def _write_overlays(self, folder: Path) -> list[Path]:
        """``folder/<camera>.mp4``: the videos' frames with the reprojected keypoints and the detections."""
        claim_folder(folder, OVERLAYS)
        detector = self.session.detector
        colours = keypoint_colours(len(detector.keypoints))
        edges = edge_indices(detector.meta.recorded_skeleton(), detector.keypoints)
        got, files = self.raw, [overlay_file(folder, name) for name in self.videos]
        rate = [video.frame_rate(p) for p in self.videos.values()]
        writers = [video.VideoWriter(f, r) for f, r in zip(files, rate)]
        try:
            start = int(got.fnums[0]) if len(got.fnums) else 0
            stop = int(got.fnums[-1]) + 1 if len(got.fnums) else 0
            batches = video.synchronized_batches(list(self.videos.values()), self.config.chunks.batch, start,
                                                 stop, self.session.offsets or None)
            t = 0
            for _, frames in video.prefetch(batches):  # decoded as the detection decoded them
                for views in frames:
                    for c, w in enumerate(writers):
                        w.write(draw_overlay(views[c], got.reproj[t, c], got.uv[t, c], got.used[t, c],
                                             colours, edges))
                    t += 1
        finally:
            for w in writers:
                w.close()
        return files

    def report(self, out: Path, raw: Path, ranked: Path) -> list[str]:
        """The lines that say what was written (``warning: ...`` among them)."""
        valid, median, passing = self.fractions()
        what = "filtered " if self.filtered is not None else ""
        lines = [f"wrote {self.frames} {what}frames to {out} (units: {self.session.units})"]
        weight = self.config.readout.min_weight
        lines += [f"  {kp}: {keypoint_line(valid[k], median[k], passing[k], weight, self.frames)}"
                  for k, kp in enumerate(self.keypoints)]
        hint = empty_result_hint(valid, passing, self.config.readout.min_weight, self.frames, out)
        if hint:
            lines.append(f"warning: {hint}")
        if self.filtered is not None:
            info = self.filtered.info
            lines.append(f"raw points in {raw}; the filter rejected {info['rejected']} jump(s) and bridged "
                         f"{info['bridged']} point(s) (ncams 0 in {out.name})")
        lines.append(f"frames ranked by doubt in {ranked}")
        if self.config.outputs.overlay:
            lines.append(f"overlay videos in {self.config.outputs.overlay}")
        return lines


def keypoint_line(valid: float, median_px: float, passing: float, min_weight: float, frames: int) -> str:
    """A keypoint's line of the summary: how often it was triangulated (``valid``, a fraction of the
    frames), its median error, and for the frames without a point, why and which option changes it
    (``passing``: the fraction of frames with two views above ``min_weight``)."""
    text = f"{100 * valid:.0f}% valid"
    if valid > 0:
        text += f", median error {median_px:.2f} px"
    if valid >= 1 or not frames:
        return text
    reasons = []
    few = 1.0 - passing  # frames where fewer than two views pass --min-weight
    if few > 0:
        change = ("lower --min-weight (0 uses every view, weighted)" if min_weight > 0 else
                  "the detector is not confident there: train on more labelled frames like these")
        reasons.append(f"{100 * few:.0f}% of frames have fewer than 2 views with a confidence above "
                       f"--min-weight {min_weight:g} ({change})")
    rest = passing - valid  # enough views, but no point
    if rest > 1e-9:
        reasons.append(f"in {100 * rest:.0f}% of frames its views triangulate to no valid point (rays near "
                       "parallel or the point behind a camera: check --calibration, --video-region and "
                       "--crop)")
    return text + "; no point: " + "; ".join(reasons)


def empty_result_hint(valid: list[float], passing: list[float], min_weight: float, frames: int,
                      path: Path) -> str | None:
    """What to say when no keypoint got a 3D point in any frame (the CSV is all ``nan``), else None."""
    if not frames or any(valid):
        return None
    if not any(passing):
        why = ("no keypoint has two views with a confidence above --min-weight "
               f"{min_weight:g} in any frame")
    else:
        why = "the views of every keypoint triangulate to no valid point"
    return (f"every keypoint is 0% valid ({why}), so {path} holds only nan: the detector finds "
            "nothing confident in these videos. A briefly trained model does this: train longer (check it "
            "with 's3k evaluate RUN DATASET' first), make sure the videos show what it was trained on, and "
            + ("lower --min-weight (0 uses every view)" if min_weight > 0
               else "check that the calibration matches the videos"))
