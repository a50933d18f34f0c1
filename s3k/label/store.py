"""The labels of a dataset as the labelling app edits them: every edit saved at once, versioned, logged.

:class:`LabelStore` holds the dataset's ``labels.csv`` as arrays (every row, occluded marks included) and
applies edits to it. Each save

1. takes the dataset's label lock (:func:`s3k.base.fileio.file_lock` on ``.labels.lock``), so that two
   processes (the app and ``s3k label propagate``) never interleave,
2. reloads the table if another process changed it since it was last read,
3. refuses an edit made against an older version of the frame (:class:`StaleVersion`, the app's HTTP 409):
   each frame has a version, the number of saves it has had, and every save says which version it edited,
4. rewrites ``labels.csv`` atomically (:func:`s3k.base.fileio.atomic_path`: a process killed at any moment
   leaves the old table or the new one), then appends the edit to the history log ``labels-history.jsonl`` and
   flushes it to disk, and only then returns, so an acknowledged edit is on disk.

The history log is append-only JSON lines, one per save: time, labeller, frame, the version the save made,
where it came from (``click``, ``drag``, ``accept``, ``propagate``...), the ``batch`` id shared by the
entries of one save (a propagation writes many frames at once) and each changed label before and after.
The frames' versions are read back from it when a store opens. An undo (:meth:`LabelStore.undo`, the app's
Ctrl+Z; :meth:`LabelStore.undo_batch`, ``s3k label propagate --undo``) is an entry of its own that puts the
``before`` labels back and names the version it reverts (``undoes``), so nothing is ever erased from the log.
A redo (:meth:`LabelStore.redo`, Ctrl+Shift+Z or Ctrl+Y) reverts the latest undo not yet redone, as an entry
naming it (``redoes``); a new edit of the frame empties its redo stack, as in any editor.
"""

from __future__ import annotations

import csv
import io
import json
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path, file_lock
from s3k.data.problems import DatasetError, Problems
from s3k.data.sources import IMAGE_SOURCES
from s3k.data.tables import (
    FRAMES_FILE,
    LABELS_COLUMNS,
    LABELS_FILE,
    SPLITS,
    read_frames,
    read_labels,
    read_metadata,
)

__all__ = ["HISTORY_FILE", "LOCK_FILE", "Edit", "LabelStore", "StaleVersion"]

HISTORY_FILE = "labels-history.jsonl"
LOCK_FILE = ".labels.lock"


@dataclass
class Edit:
    """One label change: set ``(u, v)`` (``visible``), mark occluded (``visible=False``, ``u, v`` optional)
    or remove the label (``remove=True``)."""

    camera: str
    keypoint: str
    u: float | None = None
    v: float | None = None
    visible: bool = True
    remove: bool = False


class StaleVersion(UserError):
    """A save made against an older version of a frame than the stored one; nothing was written."""

    def __init__(self, frame: int, edited: int, current: int) -> None:
        self.frame, self.edited, self.current = frame, edited, current
        super().__init__(f"frame {frame} changed since version {edited} was loaded (now version {current})",
                         hint="reload the frame and repeat the edit")


def _num(x: float) -> str:
    return repr(float(x))  # shortest text that reads back to the same float64


class LabelStore:
    """The labels of the dataset folder ``root`` (whose tables :class:`s3k.data.Dataset` has checked).

    Args:
        root: dataset folder.
        keypoints, cameras: the dataset's names (``s3k.json``).
        image_size: ``(W, H)`` of the stored images; a visible label must lie inside.
        labeller: name written into the history with each save.
        promote: a frame of the ``unlabelled`` split that gets a label moves to ``labelled`` (frames.csv).
    """

    def __init__(self, root: str | Path, meta: Any, labeller: str | None = None,
                 promote: bool = True) -> None:
        self.root = Path(root)
        self.meta = meta
        self.keypoints = list(meta.keypoints)
        self.cameras = list(meta.cameras)
        self.image_size = tuple(meta.image_size)
        self.labeller = labeller or os.environ.get("USER") or "unknown"
        self.promote = promote
        self._stamp: tuple[Any, ...] | None = None
        self._mutex = threading.RLock()  # the app's request threads share one store
        with file_lock(self.root / LOCK_FILE):
            self._load()

    # -- reading -----------------------------------------------------------------------------------------

    @classmethod
    def open(cls, root: str | Path, labeller: str | None = None, promote: bool = True) -> LabelStore:
        """Open the labels of a dataset folder (its tables are validated first)."""
        P = Problems()
        meta = read_metadata(Path(root), P, IMAGE_SOURCES)
        if meta is None or P.errors:
            raise DatasetError(root, P.errors)
        return cls(root, meta, labeller, promote)

    def _file_stamp(self) -> tuple[Any, ...]:
        out: list[Any] = []
        for name in (LABELS_FILE, FRAMES_FILE, HISTORY_FILE):
            try:
                st = os.stat(self.root / name)
                out.append((st.st_mtime_ns, st.st_size, st.st_ino))
            except FileNotFoundError:
                out.append(None)
        return tuple(out)

    def _load(self) -> None:
        P = Problems()
        frames = read_frames(self.root, P)
        if frames is None or P.errors:
            raise DatasetError(self.root, P.errors)
        labels = read_labels(self.root, self.meta, frames, P)
        if P.errors:
            raise DatasetError(self.root, P.errors)
        self.frames = frames
        self.uv = labels.uv  # (N, C, K, 2) float64, NaN where absent (or occluded without a position)
        self.present = labels.present
        self.visible = labels.visible
        self.versions: dict[int, int] = {}
        for entry in self._read_history():
            f = entry.get("frame")
            if isinstance(f, int):
                self.versions[f] = max(self.versions.get(f, 0), int(entry.get("version", 0)))
        self._stamp = self._file_stamp()

    def _read_history(self) -> list[dict[str, Any]]:
        path = self.root / HISTORY_FILE
        if not path.is_file():
            return []
        entries = []
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by a crash before it was acknowledged
            if isinstance(entry, dict):
                entries.append(entry)
        return entries

    def refresh(self) -> None:
        """Reload the tables if another process changed them."""
        with self._mutex:
            if self._file_stamp() != self._stamp:
                with file_lock(self.root / LOCK_FILE):
                    self._load()

    def row(self, frame: int) -> int:
        if frame not in self.frames.row_of:
            raise UserError(f"frame {frame} is not listed in {self.root / FRAMES_FILE}")
        return self.frames.row_of[frame]

    def version(self, frame: int) -> int:
        return self.versions.get(int(frame), 0)

    def split(self, frame: int) -> str:
        return str(self.frames.splits[self.row(frame)])

    def frame_labels(self, frame: int) -> dict[str, Any]:
        """The labels of a frame: ``{"frame", "version", "split", "labels": [{camera, keypoint, u, v,
        visible}]}`` (``u``, ``v`` None for an occluded mark without a position)."""
        i = self.row(frame)
        out = []
        for c, cam in enumerate(self.cameras):
            for k, kp in enumerate(self.keypoints):
                if self.present[i, c, k]:
                    u, v = self.uv[i, c, k]
                    out.append({"camera": cam, "keypoint": kp,
                                "u": None if not np.isfinite(u) else float(u),
                                "v": None if not np.isfinite(v) else float(v),
                                "visible": bool(self.visible[i, c, k])})
        return {"frame": int(frame), "version": self.version(frame), "split": self.split(frame),
                "labels": out}

    def arrays(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``uv (C, K, 2)`` float64 and ``mask (C, K)``: the visible labels of a frame."""
        i = self.row(frame)
        mask = self.present[i] & self.visible[i] & np.isfinite(self.uv[i]).all(-1)
        return self.uv[i].copy(), mask

    def history(self, frame: int | None = None) -> list[dict[str, Any]]:
        """The edit log, oldest first (of one frame when given)."""
        entries = self._read_history()
        return entries if frame is None else [e for e in entries if e.get("frame") == frame]

    # -- writing -----------------------------------------------------------------------------------------

    def _check(self, frame: int, edit: Edit) -> tuple[int, int]:
        if edit.camera not in self.cameras:
            raise UserError(f"unknown camera {edit.camera!r}; the dataset's cameras are {self.cameras}")
        if edit.keypoint not in self.keypoints:
            raise UserError(f"unknown keypoint {edit.keypoint!r}; the dataset's keypoints are "
                            f"{self.keypoints}")
        c, k = self.cameras.index(edit.camera), self.keypoints.index(edit.keypoint)
        if edit.remove:
            return c, k
        W, H = self.image_size
        has_uv = edit.u is not None and edit.v is not None
        if edit.visible and not has_uv:
            raise UserError(f"frame {frame}, camera {edit.camera}, keypoint {edit.keypoint}: a visible label "
                            "needs u and v")
        if has_uv:
            u, v = float(edit.u), float(edit.v)  # type: ignore[arg-type]
            if not (np.isfinite(u) and np.isfinite(v)):
                raise UserError(f"frame {frame}, camera {edit.camera}: u, v must be finite, got {u}, {v}")
            if edit.visible and not (-0.5 <= u <= W - 0.5 and -0.5 <= v <= H - 0.5):
                raise UserError(f"frame {frame}, camera {edit.camera}, keypoint {edit.keypoint}: "
                                f"({u:g}, {v:g}) is outside the {W}x{H} image")
        return c, k

    def _state(self, i: int, c: int, k: int) -> dict[str, Any] | None:
        if not self.present[i, c, k]:
            return None
        u, v = self.uv[i, c, k]
        return {"u": float(u) if np.isfinite(u) else None, "v": float(v) if np.isfinite(v) else None,
                "visible": bool(self.visible[i, c, k])}

    def save(self, frame: int, edits: list[Edit], version: int | None,
             source: str = "click") -> dict[str, Any]:
        """Apply ``edits`` to ``frame`` and write them to disk before returning.

        Args:
            frame: frame id.
            edits: the changes, applied together (one version step).
            version: the frame version the edits were made against; None skips the check (a library caller
                that owns the dataset, such as :func:`s3k.label.propagate.propagate_labels`).
            source: what made the edit, for the history.

        Returns:
            :meth:`frame_labels` after the save.

        Raises:
            StaleVersion: ``version`` is older than the stored one (nothing is written).
            UserError: an unknown frame, camera or keypoint, or a visible label outside the image.
        """
        if not edits:
            self.refresh()
            return self.frame_labels(frame)
        return self.save_many({frame: edits}, {frame: version}, source)[frame]

    def save_many(self, edits: dict[int, list[Edit]], versions: dict[int, int | None] | None = None,
                  source: str = "click", undoes: dict[int, dict[str, Any]] | None = None,
                  redoes: dict[int, dict[str, Any]] | None = None) -> dict[int, dict[str, Any]]:
        """:meth:`save` for several frames in one write of the table (``versions`` per frame). The entries of
        one call share a ``batch`` id in the history; ``undoes`` (``{frame: history entry}``, for
        :meth:`undo`) marks each frame's entry as the undoing of that one, ``redoes`` (for :meth:`redo`) as
        the redoing of that undo."""
        versions = versions or {}
        undoes = undoes or {}
        redoes = redoes or {}
        batch = f"{time.time_ns():x}-{os.getpid()}"
        edits = {f: es for f, es in edits.items() if es}  # nothing to change: no new version either
        if not edits:
            return {}
        with self._mutex, file_lock(self.root / LOCK_FILE):
            if self._file_stamp() != self._stamp:
                self._load()
            rows = {f: self.row(int(f)) for f in edits}
            for f in edits:
                want = versions.get(f)
                if want is not None and int(want) != self.version(f):
                    raise StaleVersion(int(f), int(want), self.version(f))
            checked = {f: [(e, *self._check(f, e)) for e in es] for f, es in edits.items()}
            uv, present, visible = self.uv.copy(), self.present.copy(), self.visible.copy()
            splits = self.frames.splits.copy()
            log = []
            now = time.strftime("%Y-%m-%dT%H:%M:%S%z")
            for f, items in checked.items():
                i = rows[f]
                changes = []
                for e, c, k in items:
                    before = self._state(i, c, k) if present[i, c, k] else None
                    if e.remove:
                        present[i, c, k], visible[i, c, k], uv[i, c, k] = False, False, np.nan
                    else:
                        present[i, c, k], visible[i, c, k] = True, bool(e.visible)
                        uv[i, c, k] = (np.nan, np.nan) if e.u is None or e.v is None else (e.u, e.v)
                    after = None
                    if present[i, c, k]:
                        pu, pv = uv[i, c, k]
                        after = {"u": float(pu) if np.isfinite(pu) else None,
                                 "v": float(pv) if np.isfinite(pv) else None,
                                 "visible": bool(visible[i, c, k])}
                    changes.append({"camera": e.camera, "keypoint": e.keypoint, "before": before,
                                    "after": after})
                entry: dict[str, Any] = {"time": now, "labeller": self.labeller, "frame": int(f),
                                         "version": self.version(f) + 1, "source": source, "batch": batch,
                                         "changes": changes}
                if f in redoes:
                    entry["redoes"] = int(redoes[f]["version"])
                undone = undoes.get(f)
                if undone is not None:
                    entry["undoes"] = int(undone["version"])
                    moved = undone.get("split")
                    if isinstance(moved, dict) and moved.get("before") in SPLITS and \
                            splits[i] == moved.get("after") and not (present[i] & visible[i]).any():
                        splits[i] = moved["before"]  # back to the split it had before the undone labels
                        entry["split"] = {"before": moved["after"], "after": moved["before"]}
                elif self.promote and splits[i] == "unlabelled" and (present[i] & visible[i]).any():
                    splits[i] = "labelled"
                    entry["split"] = {"before": "unlabelled", "after": "labelled"}
                log.append(entry)
            if (splits != self.frames.splits).any():
                self._write_splits(splits)
            self._write_table(uv, present, visible)
            self._append_history(log)
            self.uv, self.present, self.visible = uv, present, visible
            self.frames.splits = splits
            for entry in log:
                self.versions[entry["frame"]] = entry["version"]
            self._stamp = self._file_stamp()
            return {f: self.frame_labels(int(f)) for f in edits}

    # -- undoing -----------------------------------------------------------------------------------------

    def last_edit(self, frame: int) -> dict[str, Any] | None:
        """The frame's latest history entry that is not an undo and has not been undone (None: nothing left
        to undo). Undos are themselves entries (``undoes``: the version they revert), so the history stays
        append-only and repeated undos step back one edit at a time."""
        undone: set[int] = set()
        for entry in reversed(self.history(int(frame))):
            if "undoes" in entry:
                undone.add(int(entry["undoes"]))
            elif int(entry.get("version", -1)) not in undone:
                return entry
        return None

    @staticmethod
    def _reverting(entry: dict[str, Any]) -> list[Edit]:
        """The edits that put back the labels a history entry changed."""
        out = []
        for change in entry.get("changes", []):
            before = change.get("before")
            if before is None:
                out.append(Edit(change["camera"], change["keypoint"], remove=True))
            else:
                out.append(Edit(change["camera"], change["keypoint"], before.get("u"), before.get("v"),
                                bool(before.get("visible", True))))
        return out

    def last_undo(self, frame: int) -> dict[str, Any] | None:
        """The frame's latest undo that no redo has reverted yet, if no edit came after it (None: nothing
        to redo). Undos stack up, each redo takes the top one off, any other edit empties the stack."""
        stack: list[dict[str, Any]] = []
        for entry in self.history(int(frame)):
            if "undoes" in entry:
                stack.append(entry)
            elif "redoes" in entry:
                stack = [e for e in stack if int(e.get("version", -1)) != int(entry["redoes"])]
            else:
                stack = []
        return stack[-1] if stack else None

    def undo(self, frame: int, version: int | None = None) -> dict[str, Any]:
        """Revert the frame's latest edit (:meth:`last_edit`), as a new version; returns
        :meth:`frame_labels`. ``version``: the frame version the undo was asked against (as for :meth:`save`).

        Raises:
            StaleVersion: ``version`` is older than the stored one.
            UserError: the frame has no edit left to undo.
        """
        return self._step(frame, version, redo=False)

    def redo(self, frame: int, version: int | None = None) -> dict[str, Any]:
        """Revert the frame's latest undo not yet redone (:meth:`last_undo`), as :meth:`undo` does an edit;
        UserError when there is none (no undo, or an edit since)."""
        return self._step(frame, version, redo=True)

    def _step(self, frame: int, version: int | None, redo: bool) -> dict[str, Any]:
        with self._mutex:  # save_many takes the file lock and refuses the step if another process saved
            self.refresh()
            if version is not None and int(version) != self.version(frame):
                raise StaleVersion(int(frame), int(version), self.version(frame))
            entry = self.last_undo(frame) if redo else self.last_edit(frame)
            if entry is None:
                what = "undone edit to redo" if redo else "edit to undo"
                raise UserError(f"frame {frame}: no {what} in {self.root / HISTORY_FILE}")
            done = str(entry.get("source", "edit"))
            source = (f"redo {done.removeprefix('undo ')}" if redo else f"undo {done}")[:60]
            return self.save_many({frame: self._reverting(entry)}, {frame: self.version(frame)}, source,
                                  undoes=None if redo else {frame: entry},
                                  redoes={frame: entry} if redo else None)[frame]

    def undo_batch(self, batch: str, source: str = "undo") -> list[int]:
        """Revert every frame's entry of one :meth:`save_many` call (e.g. a propagation); returns the frames.

        Raises:
            UserError: no entry has that batch id, or a frame was edited since (named: undo that first).
        """
        with self._mutex:
            self.refresh()
            log = self.history()
            undone = {(e.get("frame"), e["undoes"]) for e in log if "undoes" in e}
            entries = [e for e in log if e.get("batch") == batch and "undoes" not in e
                       and (e.get("frame"), e.get("version")) not in undone]
            if not entries:
                raise UserError(f"no edit {batch!r} in {self.root / HISTORY_FILE}")
            for entry in entries:
                last = self.last_edit(int(entry["frame"]))
                if last != entry:
                    raise UserError(f"frame {entry['frame']} was edited after {entry.get('source')!r} "
                                    f"(now version {self.version(int(entry['frame']))}); nothing was undone",
                                    hint="undo the later edits of that frame first (Ctrl+Z in s3k label)")
            frames = [int(e["frame"]) for e in entries]
            self.save_many({int(e["frame"]): self._reverting(e) for e in entries},
                           {f: self.version(f) for f in frames}, source,
                           undoes={int(e["frame"]): e for e in entries})
            return sorted(int(e["frame"]) for e in entries)

    def _write_table(self, uv: np.ndarray, present: np.ndarray, visible: np.ndarray) -> None:
        lines = [",".join(LABELS_COLUMNS)]
        for i in np.argsort(self.frames.ids, kind="stable"):
            f = int(self.frames.ids[i])
            for c, cam in enumerate(self.cameras):
                for k, kp in enumerate(self.keypoints):
                    if not present[i, c, k]:
                        continue
                    u, v = uv[i, c, k]
                    text = (_num(u), _num(v)) if np.isfinite(u) and np.isfinite(v) else ("", "")
                    lines.append(f"{f},{cam},{kp},{text[0]},{text[1]},{int(visible[i, c, k])}")
        with atomic_path(self.root / LABELS_FILE) as tmp:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write("\n".join(lines) + "\n")
                fh.flush()
                os.fsync(fh.fileno())

    def _write_splits(self, splits: np.ndarray) -> None:
        """Rewrite frames.csv with new splits, keeping every other cell and comment line as it was."""
        path = self.root / FRAMES_FILE
        text = path.read_text(encoding="utf-8")
        out, header = [], None
        for line in text.splitlines():
            if not line.strip() or line.lstrip().startswith("#"):
                out.append(line)
                continue
            cells = next(csv.reader([line]))
            if header is None:
                header = [h.strip() for h in cells]
                out.append(line)
                continue
            try:
                frame = int(cells[header.index("frame")])
            except (ValueError, IndexError):
                out.append(line)
                continue
            i = self.frames.row_of.get(frame)
            col = header.index("split")
            if i is None or cells[col] == splits[i] or splits[i] not in SPLITS:
                out.append(line)
                continue
            cells[col] = str(splits[i])
            buf = io.StringIO()
            csv.writer(buf, lineterminator="").writerow(cells)
            out.append(buf.getvalue())
        with atomic_path(path) as tmp:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write("\n".join(out) + "\n")
                fh.flush()
                os.fsync(fh.fileno())

    def _append_history(self, entries: list[dict[str, Any]]) -> None:
        data = "".join(json.dumps(e, separators=(",", ":")) + "\n" for e in entries)
        fd = os.open(self.root / HISTORY_FILE, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            size = os.fstat(fd).st_size
            if size and os.pread(fd, 1, size - 1) != b"\n":
                data = "\n" + data  # after a line cut short by a crash: start a new line

            os.write(fd, data.encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)
