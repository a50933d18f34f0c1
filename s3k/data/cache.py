"""The decoded-image cache of a dataset: ``uint8 (N, C, H, W, 3)``, filled frame by frame on first use.

With ``mode="disk"`` the cache is a sparse memmap under ``DATASET/.cache/`` (or ``$S3K_CACHE_DIR``, or the
user's cache folder for a read-only dataset), named by a fingerprint of the image files and the output size,
so that processes and runs share it and a changed image file is never served stale. ``"memory"`` keeps it in
the process; ``"none"`` decodes on every request.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.fileio import file_lock
from s3k.data.problems import DatasetWarning
from s3k.data.tables import CACHE_DIR, FORMAT_VERSION

CACHE_MODES = ("disk", "memory", "none")


def fingerprint(parts: list[Any], file_items: list[str]) -> str:
    """16 hex digits identifying the cached pixels: ``parts`` (JSON-able: format version, crop, size, cameras,
    frame ids) and one ``path:size:mtime`` item per image file."""
    h = hashlib.sha1(json.dumps([FORMAT_VERSION, *parts]).encode())
    for item in file_items:
        h.update(item.encode())
    return h.hexdigest()[:16]


def cache_folders(dataset: Path) -> list[Path]:
    """Where the disk cache of ``dataset`` may live, in order of preference: ``$S3K_CACHE_DIR`` if set, else
    ``DATASET/.cache`` and, for read-only datasets, the user's cache folder (file names there include a hash
    of the dataset path)."""
    tag = hashlib.sha1(str(dataset.resolve()).encode()).hexdigest()[:8]
    if os.environ.get("S3K_CACHE_DIR"):
        return [Path(os.environ["S3K_CACHE_DIR"]) / tag]
    user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "s3k" / tag
    return [dataset / CACHE_DIR, user]


class ImageCache:
    """Decoded images of ``shape = (N, C, H, W, 3)``; ``filled (N,)`` marks the frames decoded.

    Args:
        mode: ``"disk" | "memory" | "none"``.
        shape: ``(N, C, H, W, 3)``.
        name: file name stem of the disk cache (fingerprint and size).
        folders: candidate folders of the disk cache (:func:`cache_folders`).
    """

    def __init__(self, mode: str, shape: tuple[int, ...], name: str, folders: list[Path]) -> None:
        if mode not in CACHE_MODES:
            raise ValueError(f"cache must be one of {list(CACHE_MODES)}, got {mode!r}")
        self.mode, self.shape, self.name, self.folders = mode, shape, name, folders
        self.array: Any = None  # (N, C, H, W, 3) uint8 array or memmap, created on first use
        self.filled: Any = None  # (N,) uint8, 1 where a frame is decoded
        self._lock = threading.Lock()

    def open(self) -> bool:
        """Create or attach the cache (once); False when ``mode="none"``."""
        if self.array is not None:
            return True
        if self.mode == "none":
            return False
        if self.mode == "disk":
            failures = []
            for folder in self.folders:
                try:
                    self._open_disk(folder / self.name)
                    return True
                except OSError as exc:
                    failures.append(f"{folder}: {exc}")
            warnings.warn(
                f"cannot write the image cache ({'; '.join(failures)}); caching in memory instead",
                DatasetWarning,
                stacklevel=4,
            )
        self.array = np.zeros(self.shape, dtype=np.uint8)  # pages are allocated on first write
        self.filled = np.zeros(self.shape[0], dtype=np.uint8)
        return True

    def _open_disk(self, base: Path) -> None:
        base.parent.mkdir(parents=True, exist_ok=True)
        data_path, flag_path = base.with_suffix(".u8"), base.with_suffix(".filled")
        n = self.shape[0]
        # Processes sharing the cache (DDP ranks, parallel runs) must not both create it: one truncating the
        # file another already writes to would leave frames flagged as decoded but black.
        with file_lock(base.with_suffix(".lock")):
            sizes = {data_path: int(np.prod(self.shape)), flag_path: n}
            if not all(p.exists() and p.stat().st_size == size for p, size in sizes.items()):
                for p, size in sizes.items():
                    with open(p, "wb") as f:
                        f.truncate(size)  # sparse: disk is used as frames are decoded
            self.filled = np.memmap(flag_path, dtype=np.uint8, mode="r+", shape=(n,))
            self.array = np.memmap(data_path, dtype=np.uint8, mode="r+", shape=self.shape)

    def missing(self, rows: np.ndarray) -> np.ndarray:
        """The distinct ``rows`` not decoded yet."""
        return np.unique(rows[self.filled[rows] == 0])

    def fill(self, rows: np.ndarray, decode: Callable[[np.ndarray, np.ndarray, np.ndarray], None]) -> None:
        """Decode ``rows`` not yet decoded with ``decode(rows, out, out_rows)``, which writes into
        ``out[out_rows]``."""
        with self._lock:
            rows = rows[self.filled[rows] == 0]
            if not len(rows):
                return
            decode(rows, self.array, rows)
            if isinstance(self.array, np.memmap):
                self.array.flush()
            self.filled[rows] = 1  # only after the pixels are written, for other processes sharing the file

    def read(self, rows: np.ndarray) -> np.ndarray:
        """``uint8 (len(rows), C, H, W, 3)``, a copy (fancy indexing copies; asarray drops the memmap
        type)."""
        return np.asarray(self.array[rows])
