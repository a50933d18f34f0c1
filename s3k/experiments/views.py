"""The datasets of a sweep: rendered pools, the frames each run picks, and views of a pool.

A *pool* is one rendered dataset shared by many runs; a *view* is a dataset folder holding one run's frames
of a pool. Views are read and written through the data layer (:class:`s3k.data.Dataset`,
:class:`s3k.data.DatasetWriter`), so they follow the dataset format wherever it goes; only the image folder
is replaced by a symbolic link to the pool's, so a view costs a few kilobytes of disk.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import file_lock
from s3k.base.messages import say
from s3k.data import Dataset, DatasetWriter
from s3k.experiments.grid import LABEL_CHOICES, PoolSpec
from s3k.label.suggest import POSE_ORDERS

#: frames.csv columns that group frames for a stratified pick, in order of preference.
GROUP_COLUMNS = ("segment", "instance")

#: The image folder of datasets written by :class:`s3k.data.DatasetWriter` (``images/<camera>/...``).
_IMAGES = "images"


def ensure_pool(data_dir: Path, pool: PoolSpec, workers: int | None = None, progress: bool = True,
                log: Callable[[str], None] = say) -> tuple[Path, bool]:
    """Render ``pool`` into ``data_dir/pool.name`` unless it is there; returns (path, rendered now).

    A process that finds the pool being rendered by another waits for it (a lock on ``.NAME.lock`` beside
    the pool); the pool is rendered into ``NAME.tmp`` and renamed when complete, so it is there entirely or
    not at all.
    """
    from s3k.sim.generate import simulate

    path = data_dir / pool.name
    if (path / "s3k.json").is_file():
        return path, False
    data_dir.mkdir(parents=True, exist_ok=True)
    with file_lock(data_dir / f".{pool.name}.lock"):  # hidden: data/ lists datasets only
        if (path / "s3k.json").is_file():  # rendered by the process we waited for
            return path, False
        tmp = data_dir / f"{pool.name}.tmp"
        log(f"rendering {pool.name} ({pool.images()} images)")
        t0 = time.perf_counter()
        simulate(pool.simulate_config(), tmp, workers=workers, progress=progress, overwrite=True)
        os.replace(tmp, path)
        log(f"rendered {pool.name} in {time.perf_counter() - t0:.0f} s")
        return path, True


def stratified_pick(ids: np.ndarray, groups: np.ndarray | None, n: int,
                    rng: np.random.Generator) -> np.ndarray:
    """``n`` of ``ids`` drawn round-robin over ``groups`` (each group shuffled by ``rng``), sorted.

    The picks of a larger ``n`` contain those of a smaller one (same ``rng`` state), so labelled sets nest.

    Args:
        ids: (N,) frame ids.
        groups: (N,) group label per frame (distractor segment, object instance) or None (one group).
        n: how many to pick (at most N).
        rng: random generator.

    Returns:
        (n,) sorted frame ids.
    """
    ids = np.asarray(ids)
    if n > len(ids):
        raise ValueError(f"cannot pick {n} frames from {len(ids)}")
    groups = np.zeros(len(ids), int) if groups is None else np.asarray(groups)
    queues = []
    for g in sorted(set(groups.tolist()), key=str):
        members = ids[groups == g]
        queues.append(list(members[rng.permutation(len(members))]))
    order: list[int] = []
    while len(order) < n:
        for q in queues:
            if q and len(order) < n:
                order.append(int(q.pop(0)))
    return np.sort(np.asarray(order, dtype=np.int64))


def select_frames(pool: Dataset, labelled: int, unlabelled: int, seed: int,
                  data_seed: int = 0, choice: str = "random") -> dict[str, np.ndarray]:
    """The frames of one run: ``labelled`` chosen by run ``seed``, ``unlabelled`` fixed, every test frame.

    Both choices are stratified over distractor segments / object instances (the first of
    :data:`GROUP_COLUMNS` the pool has), so "full" mode keeps labels spread over the timeline and every
    training instance keeps its share. With ``choice="coverage"`` or ``"representative"`` the labelled frames
    are the pool's in that labelling app's pose order instead (:func:`pose_pick`).

    Returns:
        ``{"labelled": (L,), "unlabelled": (U,), "test": (T,)}`` frame ids (the pool's order for test).
    """
    group = next((c for c in GROUP_COLUMNS if c in pool.frame_columns), None)
    out = {}
    if choice not in LABEL_CHOICES:
        raise ValueError(f"label choice: unknown {choice!r} ({', '.join(LABEL_CHOICES)})")
    for split, n, rng in (("labelled", labelled, np.random.default_rng([data_seed, seed, 1])),
                          ("unlabelled", unlabelled, np.random.default_rng([data_seed, 2]))):
        ids = pool.frames(split)
        if n > len(ids):
            raise ValueError(f"{pool.path}: run needs {n} {split} frames, the dataset has {len(ids)}")
        if split == "labelled" and choice != "random":
            out[split] = pose_pick(pool, ids, n, rng, choice)
            continue
        groups = None if group is None else pool.column(group, ids)
        out[split] = stratified_pick(ids, groups, n, rng)
    out["test"] = pool.frames("test")
    return out


def pose_pick(pool: Dataset, ids: np.ndarray, n: int, rng: np.random.Generator,
              choice: str = "coverage") -> np.ndarray:
    """``n`` of ``ids`` as a labeller following one of the labelling app's pose rankings picks them: a first
    frame drawn by ``rng``, then, with ``choice="coverage"`` (*poses not yet labelled, farthest first*,
    :func:`s3k.label.suggest.coverage_order`), each frame the farthest in pose from those already picked, or
    with ``"representative"`` (*poses in proportion*, :func:`s3k.label.suggest.representative_order`) the
    frame that best stands for the poses not yet near a picked one. The poses are the pool's true 3D
    keypoints, standing for a run that places the object well; the picks of a larger ``n`` contain those of
    a smaller one. Sorted.

    Raises:
        ValueError: the pool has no 3D points for these frames, or ``choice`` is not a pose order.
    """
    if choice not in POSE_ORDERS:
        raise ValueError(f"label choice: {choice!r} is not a pose order ({', '.join(POSE_ORDERS)})")
    ids = np.asarray(ids, dtype=np.int64)
    points = pool.points3d(ids)
    if points is None:
        raise ValueError(f"{pool.path}: no 3D points, which the {choice} choice of labelled frames needs")
    X = np.where(points[1][..., None], points[0], np.nan)
    if n <= 0:
        return np.zeros(0, np.int64)
    first = int(rng.integers(len(ids)))
    others = {int(f): x for f, x in zip(ids, X, strict=True) if f != ids[first]}
    rest = POSE_ORDERS[choice](others, [X[first]], limit=n - 1)
    return np.sort(np.asarray([ids[first]] + [f for f, _ in rest[: n - 1]], dtype=np.int64))


def write_frames(dataset: Dataset, out: Path, splits: Mapping[int, str], chunk: int = 64,
                 images: bool = True, **writer_args: Any) -> Path:
    """Write the frames ``splits`` (frame id -> split in ``out``) of ``dataset`` as a new dataset ``out``.

    Every table a dataset holds goes across through the public reader and writer: calibration, labels
    (those the reader keeps: labelled, visible and inside the image), 3D points and the extra frames.csv
    columns, in ``dataset``'s frame order. Images are decoded and written again (PNG is lossless, so the
    pixels are the same); with ``images=False`` none are (the caller links them). ``writer_args`` go to
    :class:`DatasetWriter` (e.g. ``source``, ``overwrite``).
    """
    ids = np.asarray([f for f in dataset.frames().tolist() if f in splits], dtype=np.int64)
    columns = list(dataset.frame_columns)
    writer = DatasetWriter(out, dataset.keypoints, dataset.cameras, dataset.image_size, dataset.units,
                           per_frame_calibration=not dataset.static_calibration,
                           skeleton=dataset.skeleton or None, description=dataset.description,
                           tables_only=not images, **writer_args)
    for start in range(0, len(ids), chunk):
        part = ids[start:start + chunk]
        pictures = dataset.images(part) if images else None  # (B, C, H, W, 3)
        cams = dataset.calibration(part, dtype=np.float64)  # (B, C), exact
        uv, mask = dataset.labels(part)  # (B, C, K, 2), (B, C, K)
        points = dataset.points3d(part)  # (B, K, 3), (B, K) or None
        X = None if points is None else np.where(points[1][..., None], points[0], np.nan)
        extra = {c: dataset.column(c, part) for c in columns}
        for b, frame in enumerate(part.tolist()):
            writer.add_frame(frame, splits[frame], None if pictures is None else pictures[b], cams[b],
                             labels=(uv[b], mask[b]), points3d=None if X is None else X[b],
                             extra={c: v[b] for c, v in extra.items()})
    return writer.close()


def link_images(view_dir: Path, pool: Dataset) -> None:
    """Replace the image folder of ``view_dir`` (written with a subset of ``pool``'s images) by a link to
    ``pool``'s, which holds the same pictures under the same names."""
    shutil.rmtree(view_dir / _IMAGES)
    os.symlink(os.path.relpath(pool.path / _IMAGES, view_dir), view_dir / _IMAGES, target_is_directory=True)


def make_view(pool: Dataset, view_dir: Path, frames: Mapping[str, np.ndarray],
              note: dict | None = None) -> Path:
    """A dataset folder holding ``frames`` (split -> ids) of ``pool``, with the splits given.

    The tables hold those frames only; ``s3k.json``'s ``source`` names the pool (``view_of``, relative) and
    ``note``. The images are a link to the pool's (:func:`link_images`). Built in a temporary folder and
    renamed, so it is complete or absent; an existing view is returned as it is.

    Raises:
        UserError: the pool does not store PNG images (a view links image files).
    """
    if (view_dir / "s3k.json").is_file():
        return view_dir
    kind = (pool.metadata.get("images") or {}).get("type", "png")
    if kind != "png":
        raise UserError(f"{pool.path}: views need PNG images, the dataset has {kind!r}")
    splits = {int(f): split for split, ids in frames.items() for f in np.asarray(ids).tolist()}
    view_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = view_dir.with_name(f"{view_dir.name}.{os.getpid()}.tmp")
    source = {"view_of": os.path.relpath(pool.path, view_dir), "pool_source": pool.source, **(note or {})}
    write_frames(pool, tmp, splits, images=False, source=source, overwrite=True)
    link_images(tmp, pool)
    Dataset.open(tmp, cache="none")  # every image resolves through the link
    try:
        os.rename(tmp, view_dir)
    except OSError:  # another process made the same view first
        shutil.rmtree(tmp, ignore_errors=True)
    return view_dir


def drop_cache(dataset_dir: Path) -> None:
    """Remove a view's decoded-image cache (the loader's ``.cache``); it is rebuilt on demand."""
    shutil.rmtree(dataset_dir / ".cache", ignore_errors=True)
