"""Writing files so that nothing is half-written, and locking them between processes.

Every file s3k writes that a later step reads (run configs, checkpoints, summaries, caches) goes through
:func:`atomic_path`: the content is written to a temporary file beside the target and renamed over it, so a
process killed at any moment leaves either the old file or the new one. :func:`file_lock` is the one lock
between processes (an advisory ``flock``, released by the kernel when its holder dies, so a crashed process
never leaves a stale lock behind).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it over ``path``, on error remove it.

    Example:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "a.txt"
        >>> with atomic_path(target) as tmp:
        ...     _ = tmp.write_text("hello")
        >>> target.read_text()
        'hello'
    """
    path = Path(path)
    # pid in the name: two processes writing the same target never share a temporary file
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_bytes(data: bytes, path: str | Path) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(text: str, path: str | Path) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(text.encode("utf-8"), path)


def _json_default(x: Any) -> Any:
    # numpy scalars and arrays without importing numpy here
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"cannot write {type(x).__name__} as JSON")


def atomic_write_json(obj: Any, path: str | Path, indent: int | None = 2) -> None:
    """Write ``obj`` as JSON (numpy values and paths allowed) to ``path`` atomically, newline-terminated."""
    atomic_write_text(json.dumps(obj, indent=indent, default=_json_default) + "\n", path)


def read_text(path: str | Path) -> str:
    """The UTF-8 text of the file ``path`` (a leading byte-order mark dropped).

    Raises:
        UserError: the file is not UTF-8 text, naming the file, the line and the byte (a CSV saved as
            Latin-1 or Windows-1252 is the usual case).
    """
    data = Path(path).read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise UserError(f"{path}, line {line}: not UTF-8 text (byte {data[exc.start]:#04x})",
                        hint="save the file as UTF-8") from None


def open_text(path: str | Path) -> io.StringIO:
    """:func:`read_text` as a file for the ``csv`` module (line endings kept, as ``newline=""``)."""
    return io.StringIO(read_text(path), newline="")


@contextlib.contextmanager
def file_lock(path: str | Path, blocking: bool = True) -> Iterator[bool]:
    """Hold an exclusive lock on the file ``path`` (created if missing) for the ``with`` block.

    Yields True when the lock is held. With ``blocking=False`` it yields False at once when another process
    holds it (the caller then skips the work). The kernel releases the lock when the holder exits, even by a
    crash. Where ``fcntl`` does not exist (Windows) the lock always succeeds.

    Example:
        >>> import tempfile
        >>> lock = Path(tempfile.mkdtemp()) / "run.lock"
        >>> with file_lock(lock, blocking=False) as mine:
        ...     mine
        True
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield True
        return
    with open(path, "a") as f:
        flags = fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB)
        try:
            fcntl.flock(f.fileno(), flags)
        except BlockingIOError:
            yield False
            return
        try:
            f.truncate(0)
            f.write(f"{os.getpid()}\n")  # for a person looking at the folder; the lock itself is the flock
            f.flush()
            yield True
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def resolve_from(folder: str | Path, value: str | Path) -> Path:
    """A path recorded in a dataset's ``s3k.json`` (``source``): absolute as it is, relative from the dataset
    folder ``folder`` (``s3k import`` writes the paths it was given relative as relative to the dataset, so
    that a dataset moved together with its recording still finds it)."""
    path = Path(value)
    return path if path.is_absolute() else Path(folder) / path
