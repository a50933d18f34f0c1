"""Dataset generation: frame plan, parallel rendering, writing through :class:`s3k.data.DatasetWriter`.

Two seeds, kept apart: ``object_seed`` fixes the scene's look (textures, object shapes, distractor sets),
``seed`` draws the frames (poses, cameras, lighting). So datasets rendered with different ``seed`` show the
same object, and a model trained on one is tested fairly on another. Every frame is a pure function of
``(object_seed, seed, frame_id)``: its randomness comes from ``numpy.random.default_rng([seed, frame_id])``
and a scene sets its whole state before each capture, so the same seeds give the same dataset whatever the
number of worker processes. Each worker process builds its own
scene (one MuJoCo model and one OpenGL renderer); the parent writes frames in frame order.
"""

from __future__ import annotations

import dataclasses
import functools
import multiprocessing as mp
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from s3k.base.errors import UserError
from s3k.base.memory import available_memory
from s3k.base.metrics import pixel_sizes_mm
from s3k.base.outputs import check_replaceable, replace_folder
from s3k.data import DatasetWriter
from s3k.geometry import Cameras
from s3k.sim.rigs import (
    DISTANCE_LIMITS,
    ELEVATION_LIMITS,
    RIGS,
    describe_rig,
    range_problem,
    ranged_sampler,
    rig_sampler,
)
from s3k.sim.scene import NUM_INSTANCES, NUM_TRAIN_INSTANCES, CameraSampler, FrameSpec, Scene, SimFrame
from s3k.sim.scenes import SCENES, make_scene

MODES = ("start", "full")
MAX_SIZE = 8192
"""The largest image side the renderer takes (MuJoCo's offscreen buffer)."""


@dataclasses.dataclass
class SimulateConfig:
    """Everything that defines a simulated dataset.

    Attributes:
        scene: "box", "distractors", "category" or "plush" (labelled frames spread over the 7 training
            arrangements, test frames over the 3 held-out ones).
        size: image width and height in pixels.
        labelled: number of labelled frames (2D labels in every camera where the keypoint is visible).
        unlabelled: number of unlabelled frames.
        test: number of test frames (labels and ground-truth 3D stored for evaluation).
        seed: sampling seed: object poses, cameras and lighting of every frame derive from it.
        object_seed: the scene's look: box texture, category instances' shapes and textures, distractor
            sets. Fixed per scene (0) unless asked otherwise, so that ``seed`` changes the frames only.
        mode: distractors only: "start" puts all labelled frames in the first segment of the timeline, "full"
            spreads them over all training segments.
        segments: distractors only: number of training segments (distractor sets) on the timeline.
        test_segments: distractors only: number of test segments, each with a distractor set unseen in
            training.
        train_instances: category only: how many of the 12 training instances the labelled and unlabelled
            frames use (the first N); test frames use the 4 held-out instances.
        unlabelled_arrangements: plush only: the unlabelled frames are spread over this many further
            arrangements as well as the 7 training ones (each a new placement of the toys and a new camera
            rig; from arrangement 13 on, so in no test set and no grasp trial). 0: the training ones only.
        rig: how the cameras are drawn: "train" (the scene's own rig) or a rig outside its ranges, "low",
            "high", "far" or "wide" (:mod:`s3k.sim.rigs`), for test sets of cameras never seen in training.
        elevation: the cameras' elevations above the table (degrees, ``(lo, hi)``) instead of the scene's;
            a named ``rig`` is drawn relative to the rig this gives.
        distance: the cameras' distances from the aim point (metres, ``(lo, hi)``) instead of the scene's.
        fixed_rig: draw the cameras once for the whole dataset (from ``seed``), as a lab's rig stays put
            through a recording, instead of anew for every frame; the frames' poses and lighting are the
            same either way.
    """

    scene: str
    size: int = 96
    labelled: int = 10
    unlabelled: int = 2000
    test: int = 200
    seed: int = 0
    object_seed: int = 0
    mode: str = "full"
    segments: int = 6
    test_segments: int = 2
    train_instances: int = NUM_TRAIN_INSTANCES
    unlabelled_arrangements: int = 0
    rig: str = "train"
    elevation: tuple[float, float] | None = None
    distance: tuple[float, float] | None = None
    fixed_rig: bool = False

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise UserError(f"scene: unknown scene {self.scene!r}; choose from {', '.join(SCENES)}")
        if self.rig not in RIGS:
            raise UserError(f"rig (--rig): unknown camera rig {self.rig!r}; choose from {', '.join(RIGS)}")
        for name, values, limits, unit in (("elevation", self.elevation, ELEVATION_LIMITS, "degrees"),
                                           ("distance", self.distance, DISTANCE_LIMITS, "m")):
            problem = range_problem(values, limits, unit)
            if problem:
                raise UserError(f"{name} (--{name}): {problem}")
        for name in ("labelled", "unlabelled", "test"):
            if getattr(self, name) < 0:
                raise UserError(f"{name} (--{name}): frame count must be >= 0, got {getattr(self, name)}")
        if self.labelled + self.unlabelled + self.test == 0:
            raise UserError("labelled + unlabelled + test: no frames to render",
                            hint="give --labelled, --unlabelled or --test a positive count")
        if self.seed < 0 or self.object_seed < 0:
            raise UserError(f"seed, object_seed (--seed, --object-seed): must be >= 0, got {self.seed}, "
                            f"{self.object_seed}")
        if not 16 <= self.size <= MAX_SIZE:
            raise UserError(f"size (--size): images must be from 16 to {MAX_SIZE} px, got {self.size}")
        if self.mode not in MODES:
            raise UserError(f"mode (--mode): must be one of {MODES}, got {self.mode!r}")
        if self.segments < 1 or self.test_segments < 1:
            raise UserError(f"segments, test_segments (--segments, --test-segments): must be >= 1, "
                            f"got {self.segments}, {self.test_segments}")
        if self.unlabelled_arrangements < 0:
            raise UserError(f"unlabelled_arrangements (--unlabelled-arrangements): must be >= 0, got "
                            f"{self.unlabelled_arrangements}")
        if not 1 <= self.train_instances <= NUM_TRAIN_INSTANCES:
            raise UserError(f"train_instances (--train-instances): must be in [1, {NUM_TRAIN_INSTANCES}], "
                             f"got {self.train_instances}")

    def describe(self) -> dict:
        """The parameters that matter for this scene, for the dataset's metadata."""
        d = {"scene": self.scene, "size": self.size, "labelled": self.labelled, "unlabelled": self.unlabelled,
             "test": self.test, "seed": self.seed, "object_seed": self.object_seed}
        if self.scene == "distractors":
            d.update(mode=self.mode, segments=self.segments, test_segments=self.test_segments)
        if self.scene == "category":
            d.update(train_instances=self.train_instances,
                     test_instances=list(range(NUM_TRAIN_INSTANCES, NUM_INSTANCES)))
        if self.scene == "plush" and self.unlabelled_arrangements:
            d.update(unlabelled_arrangements=self.unlabelled_arrangements)
        if self.rig != "train":
            d.update(rig=self.rig)
        if self.rig != "train" or self.elevation is not None or self.distance is not None:
            d.update(cameras=describe_rig(self.cameras()))
        if self.fixed_rig:
            d.update(fixed_rig=True)
        return d

    def cameras(self) -> CameraSampler:
        """How this dataset's cameras are drawn: the scene's own rig (with ``elevation`` and ``distance``
        where given) or the one ``rig`` names relative to it."""
        train = ranged_sampler(SCENES[self.scene].cameras_sampler, self.elevation, self.distance)
        sampler = rig_sampler(train, self.rig)
        return dataclasses.replace(sampler, fixed=self.seed) if self.fixed_rig else sampler


def _spread(n: int, parts: int) -> list[int]:
    """Part index of each of ``n`` items spread evenly over ``parts`` contiguous parts."""
    return [i * parts // n for i in range(n)]


def frame_plan(cfg: SimulateConfig) -> list[FrameSpec]:
    """The frames of a dataset in frame-id order.

    ``box`` and ``category``: labelled, then unlabelled, then test frames. ``category`` cycles through the
    training instances ``0 .. train_instances - 1`` (and the held-out 12-15 for test frames).
    ``distractors``: frames follow the timeline: training segment 0 (its labelled then unlabelled frames),
    segment 1, ..., then the test segments (numbered after the training ones).
    """
    L, U, T = cfg.labelled, cfg.unlabelled, cfg.test
    specs: list[FrameSpec] = []
    if cfg.scene == "distractors":
        S = cfg.segments
        lab_seg = [0] * L if cfg.mode == "start" else _spread(L, S)
        unl_seg = _spread(U, S)
        order = sorted([(s, 0, i) for i, s in enumerate(lab_seg)]
                       + [(s, 1, i) for i, s in enumerate(unl_seg)])
        for s, kind, _ in order:
            specs.append(FrameSpec(len(specs), "labelled" if kind == 0 else "unlabelled", segment=s))
        for s in _spread(T, cfg.test_segments):
            specs.append(FrameSpec(len(specs), "test", segment=S + s))
        return specs
    if cfg.scene == "plush":
        return _plush_plan(L, U, T, cfg.unlabelled_arrangements)
    for split, n in (("labelled", L), ("unlabelled", U), ("test", T)):
        for i in range(n):
            instance = -1
            if cfg.scene == "category":
                instance = (NUM_TRAIN_INSTANCES + i % (NUM_INSTANCES - NUM_TRAIN_INSTANCES) if split == "test"
                            else i % cfg.train_instances)
            specs.append(FrameSpec(len(specs), split, instance=instance))
    return specs


def _plush_plan(L: int, U: int, T: int, extra: int = 0) -> list[FrameSpec]:
    """``plush``: arrangement by arrangement (the ``segment``), each training arrangement's labelled frames
    first, then its unlabelled ones; then the ``extra`` unlabelled arrangements' frames (numbered from
    :data:`s3k.sim.plush.FIRST_UNLABELLED_ARRANGEMENT`); then the test arrangements' frames."""
    from s3k.sim.plush import FIRST_UNLABELLED_ARRANGEMENT, NUM_ARRANGEMENTS, TRAIN_ARRANGEMENTS

    A = TRAIN_ARRANGEMENTS
    unlabelled = [a if a < A else FIRST_UNLABELLED_ARRANGEMENT + a - A for a in _spread(U, A + extra)]
    order = sorted([(a, 0) for a in _spread(L, A)] + [(a, 1) for a in unlabelled])
    specs = [FrameSpec(i, "labelled" if kind == 0 else "unlabelled", segment=a)
             for i, (a, kind) in enumerate(order)]
    for a in _spread(T, NUM_ARRANGEMENTS - A):
        specs.append(FrameSpec(len(specs), "test", segment=A + a))
    return specs


def frame_rng(seed: int, frame_id: int) -> np.random.Generator:
    """The random generator of one frame: a function of ``(seed, frame_id)`` only."""
    return np.random.default_rng([int(seed), int(frame_id)])


@functools.cache
def scene_mm_per_px(scene: str, size: int, frames: int = 200, seed: int = 0, object_seed: int = 0) -> float:
    """The median size in millimetres of one pixel at the workspace centre of ``scene`` at ``size`` px.

    The camera rigs are those of the ``frames`` test frames of ``s3k simulate SCENE --size SIZE --test FRAMES
    --seed SEED`` (no labelled or unlabelled frames): each frame's state is drawn as rendering draws it, so
    the same rigs, but nothing is rendered. A rig's pixel size is :func:`s3k.base.metrics.pixel_sizes_mm`
    (the point nearest to the cameras' optical axes, its depth over the focal length), per camera; this is
    their
    median over frames and cameras: what turns a pixel error of this scene at this size into millimetres on
    the object. The focal length grows with the image size and nothing else does, so it scales as 1 / size.
    """

    cfg = SimulateConfig(scene, size=size, labelled=0, unlabelled=0, test=frames, seed=seed,
                         object_seed=object_seed)
    rigs = []
    with make_scene(scene, size=size, seed=object_seed) as sim:
        for spec in frame_plan(cfg):
            sim.sample(spec, frame_rng(seed, spec.frame_id))
            sim.forward()
            rigs.append(sim.calibration())
    K, R, t = (np.stack(a) for a in zip(*rigs))  # (F, C, 3, 3), (F, C, 3, 3), (F, C, 3)
    cams = Cameras.from_numpy(K, None, R, t, dtype=torch.float64)
    sizes = pixel_sizes_mm(cams, 1000.0)  # (F, C); the scenes are in metres
    return float(np.median(sizes[np.isfinite(sizes)]))


# ---------------------------------------------------------------------------------------------- workers
_WORKER_SCENE: Scene | None = None


def _init_worker(scene: str, size: int, seed: int, cameras: CameraSampler) -> None:
    global _WORKER_SCENE
    cv2.setNumThreads(1)
    _WORKER_SCENE = make_scene(scene, size=size, seed=seed, cameras=cameras)  # seed: the scene's look


def _render_chunk(args: tuple[int, list[FrameSpec]]) -> list[SimFrame]:
    seed, specs = args
    assert _WORKER_SCENE is not None, "worker not initialised"
    return [_WORKER_SCENE.frame(s, frame_rng(seed, s.frame_id)) for s in specs]


def render_frames(cfg: SimulateConfig, specs: Sequence[FrameSpec], workers: int = 1,
                  chunk: int = 4) -> Iterator[SimFrame]:
    """Renders ``specs`` in order, in ``workers`` processes (in this process when ``workers <= 1``)."""
    if workers <= 1:
        with make_scene(cfg.scene, size=cfg.size, seed=cfg.object_seed, cameras=cfg.cameras()) as scene:
            for s in specs:
                yield scene.frame(s, frame_rng(cfg.seed, s.frame_id))
        return
    chunks = [(cfg.seed, list(specs[i:i + chunk])) for i in range(0, len(specs), chunk)]
    # spawn: a fresh interpreter per worker, so no OpenGL or thread state is inherited from the parent.
    ctx = mp.get_context("spawn")
    with ctx.Pool(workers, initializer=_init_worker,
                  initargs=(cfg.scene, cfg.size, cfg.object_seed, cfg.cameras())) as pool:
        for frames in pool.imap(_render_chunk, chunks):
            yield from frames


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


# ---------------------------------------------------------------------------------------------- writing
def labels_of(frame: SimFrame) -> tuple[np.ndarray, np.ndarray]:
    """2D labels of a frame for the writer: ``(uv (C, K, 2), mask (C, K))``, labelled where the keypoint
    projects inside the image (a keypoint hidden by another object is written as labelled-but-occluded)."""
    from s3k.sim.scene import in_image

    H, W = frame.images.shape[1:3]
    return frame.uv, in_image(frame.uv, frame.depth, W, H)


def simulate(cfg: SimulateConfig, out: str | Path, workers: int | None = None, progress: bool = True,
             overwrite: bool = False, png_compression: int = 1, preview: str | Path | None = None) -> dict:
    """Renders the dataset ``cfg`` into folder ``out``.

    Labelled and test frames get 2D labels (projections of the ground-truth keypoints, flagged not visible
    where another object hides them); every frame gets ground-truth 3D keypoints (for evaluation only) and its
    own calibration (the cameras move every frame).

    Args:
        cfg: what to render.
        out: dataset folder to create.
        workers: rendering processes (default: the CPUs available).
        progress: show a tqdm progress bar.
        overwrite: replace an existing non-empty folder.
        png_compression: 0-9 (1 is fast and only slightly larger).
        preview: write a contact sheet PNG of 3 frames here: the first, the middle and the last (for
            ``distractors``: first and middle training segments and a test segment; for ``category``: two
            training instances and a held-out one).

    Returns:
        A summary: ``{"path", "frames", "images", "seconds", "images_per_s"}``.
    """

    workers = default_workers() if workers is None else max(1, int(workers))
    out = check_replaceable(out, overwrite)
    check_memory(cfg, workers)
    check_disk(cfg, out)
    specs = frame_plan(cfg)
    t0 = time.perf_counter()
    with replace_folder(out, overwrite) as tmp:  # out appears complete, or stays as it was
        shown = _render_into(tmp, cfg, specs, workers, progress, png_compression, preview is not None)
    seconds = time.perf_counter() - t0
    if preview is not None:
        sheet = contact_sheet(shown, SCENES[cfg.scene].keypoints)
        cv2.imwrite(str(preview), sheet[..., ::-1])
    n_images = len(specs) * 4
    return {"path": str(out), "frames": len(specs), "images": n_images, "seconds": seconds,
            "images_per_s": n_images / seconds}


def _render_into(path: Path, cfg: SimulateConfig, specs: list[FrameSpec], workers: int, progress: bool,
                 png_compression: int, preview: bool) -> list[SimFrame]:
    """Render ``specs`` into the dataset folder ``path``; returns the frames of the preview."""

    scene_cls = SCENES[cfg.scene]
    cameras = [f"cam{i}" for i in range(4)]
    writer = DatasetWriter(
        path, scene_cls.keypoints, cameras, (cfg.size, cfg.size), units="m", per_frame_calibration=True,
        description=(scene_cls.__doc__ or "").strip().split("\n")[0],
        source={"generator": "s3k simulate", **cfg.describe()}, png_compression=png_compression,
    )
    shown: list[SimFrame] = []
    preview_ids = sorted({0, len(specs) // 2, len(specs) - 1})
    with tqdm(total=len(specs), unit="frame", desc=f"simulate {cfg.scene}", disable=not progress) as bar:
        for frame in render_frames(cfg, specs, workers=min(workers, len(specs))):
            extra = {}
            if cfg.scene in ("distractors", "plush"):
                extra["segment"] = frame.extra["segment"]
            if cfg.scene == "category":
                extra["instance"] = frame.extra["instance"]
            labels = labels_of(frame) if frame.split in ("labelled", "test") else None
            zeros = np.zeros((len(cameras), 5))
            writer.add_frame(frame.frame_id, frame.split, frame.images, (frame.K, zeros, frame.R, frame.t),
                             labels=labels, points3d=frame.points3d, visible=frame.visible, extra=extra)
            if preview and frame.frame_id in preview_ids:
                shown.append(frame)
            bar.update(1)
    writer.close()
    return shown


FRAME_BOOKKEEPING_BYTES = 4096
"""Memory a frame takes besides its images while a dataset is written (its plan, calibration, labels)."""


def memory_needed(cfg: SimulateConfig, workers: int) -> int:
    """Bytes :func:`simulate` holds at most: the frames' bookkeeping, and per worker the renderer's buffers
    (colour, depth, segmentation of one view) and a few chunks of 4-view frames in flight."""
    n = cfg.labelled + cfg.unlabelled + cfg.test
    view = cfg.size * cfg.size
    return n * FRAME_BOOKKEEPING_BYTES + workers * (view * 16 + 3 * 4 * 4 * view * 3)


def check_memory(cfg: SimulateConfig, workers: int) -> None:
    """Refuse, before anything is allocated, a dataset whose rendering would not fit in memory."""
    need, have = memory_needed(cfg, workers), available_memory()
    if have is not None and need > have:
        n = cfg.labelled + cfg.unlabelled + cfg.test
        raise UserError(f"{n} frames of {cfg.size}x{cfg.size} px with {workers} rendering processes need "
                        f"about {need / 2**30:.1f} GiB of memory; {have / 2**30:.1f} GiB are available",
                        hint="lower --size, --labelled/--unlabelled/--test or --workers")


PNG_FRACTION = 0.1
"""A lower bound on a rendered view's PNG size as a fraction of its raw RGB bytes (measured: about 0.5 at
96 px, 0.7 at 32 px)."""


def disk_needed(cfg: SimulateConfig) -> int:
    """Bytes a dataset's PNGs take at the least (4 views a frame; the tables are small beside them)."""
    n = cfg.labelled + cfg.unlabelled + cfg.test
    return int(n * 4 * (PNG_FRACTION * cfg.size * cfg.size * 3 + 100))


def check_disk(cfg: SimulateConfig, out: str | Path) -> None:
    """Refuse, before anything is rendered, a dataset whose images cannot fit on the disk that holds ``out``
    (nor the plan of its frames in memory), naming the count that makes it so."""

    where = Path(out).absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        free = shutil.disk_usage(where).free
    except OSError:
        return
    need = disk_needed(cfg)
    if need > free:
        counts = {"--labelled": cfg.labelled, "--unlabelled": cfg.unlabelled, "--test": cfg.test}
        option = max(counts, key=lambda k: counts[k])
        raise UserError(f"{option} {counts[option]}: {sum(counts.values())} frames of {cfg.size}x{cfg.size} "
                        f"px (4 views each) need at least {need / 2**30:.1f} GiB of disk; "
                        f"{free / 2**30:.1f} GiB are free at {where}", hint=f"lower {option} or --size")


# ---------------------------------------------------------------------------------------------- preview
KEYPOINT_COLOURS = [(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
                    (70, 240, 240)]


def contact_sheet(frames: Sequence[SimFrame], keypoints: Sequence[str], scale: int = 1) -> np.ndarray:
    """A grid of views (rows: frames, columns: cameras) with the keypoints drawn, ``uint8 (h, w, 3)`` RGB.

    A filled dot is a visible keypoint, a ring one that is hidden by another object or (clipped to the border)
    outside the image. A legend row names the keypoints.
    """
    if not frames:
        raise ValueError("contact_sheet: no frames")
    rows = []
    for f in frames:
        views = []
        for c in range(f.images.shape[0]):
            im = f.images[c]
            if scale != 1:
                im = cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            im = np.ascontiguousarray(im)
            H, W = im.shape[:2]
            r = max(2, W // 40)
            for k in range(f.uv.shape[1]):
                u, v = (f.uv[c, k] + 0.5) * scale - 0.5
                if not np.isfinite([u, v]).all() or f.depth[c, k] <= 0:
                    continue
                p = (int(round(np.clip(u, 0, W - 1))), int(round(np.clip(v, 0, H - 1))))
                col = KEYPOINT_COLOURS[k % len(KEYPOINT_COLOURS)]
                cv2.circle(im, p, r + 1, (255, 255, 255), -1 if f.visible[c, k] else 2, cv2.LINE_AA)
                cv2.circle(im, p, r, col, -1 if f.visible[c, k] else 1, cv2.LINE_AA)
            views.append(np.pad(im, ((1, 1), (1, 1), (0, 0)), constant_values=255))
        rows.append(np.concatenate(views, 1))
    sheet = np.concatenate(rows, 0)
    legend = np.full((18, sheet.shape[1], 3), 255, np.uint8)
    x = 6
    for k, name in enumerate(keypoints):
        col = KEYPOINT_COLOURS[k % len(KEYPOINT_COLOURS)]
        cv2.circle(legend, (x + 5, 9), 5, col, -1, cv2.LINE_AA)
        cv2.putText(legend, name, (x + 14, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        x += 24 + 7 * len(name)
    return np.concatenate([sheet, legend], 0)
