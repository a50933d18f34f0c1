"""The memory a new allocation of this process may take (:func:`available_memory`): what the memory-fit
refusals (:mod:`s3k.budget`), the image cache and a two-pass run's held frames decide by."""

from __future__ import annotations

import os
from pathlib import Path

try:
    import resource
except ImportError:  # not on Windows
    resource = None  # type: ignore[assignment]

__all__ = ["available_memory"]


def available_memory() -> int | None:
    """Bytes of memory a new allocation of this process may take, None when unknown: the least of the
    machine's available memory (Linux's MemAvailable), the room left under the process's control group's
    limit (cgroup v2 ``memory.max``, v1 ``memory.limit_in_bytes``) and under its address-space and data limits
    (``ulimit -v``, ``RLIMIT_DATA``)."""
    found = [n for n in (_meminfo_available(), _cgroup_room(), *_rlimit_room()) if n is not None]
    return max(0, min(found)) if found else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # "max": no limit


def _cgroup_room() -> int | None:
    """The limit minus the usage of the process's memory control group (the tightest of it and its parents
    that the process can see), None without a limit."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        _, controllers, rel = line.split(":", 2)
        if controllers == "":  # v2
            root, limit_name, usage_name = Path("/sys/fs/cgroup"), "memory.max", "memory.current"
        elif "memory" in controllers.split(","):
            root, limit_name, usage_name = (Path("/sys/fs/cgroup/memory"), "memory.limit_in_bytes",
                                            "memory.usage_in_bytes")
        else:
            continue
        folder = root / rel.lstrip("/")
        for candidate in (folder, *folder.parents):
            if not str(candidate).startswith(str(root)):
                break
            limit, usage = _read_int(candidate / limit_name), _read_int(candidate / usage_name)
            if limit is not None and usage is not None and limit < 2**60:
                rooms.append(limit - usage)
    return min(rooms) if rooms else None


def _rlimit_room() -> list[int | None]:
    """The room left under ``RLIMIT_AS`` (against the process's virtual size) and ``RLIMIT_DATA`` (against its
    data segment), each None when unlimited or unknown."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return []
    if resource is None:
        return []
    used = {line.split(":")[0]: int(line.split()[1]) * 1024 for line in status.splitlines()
            if line.startswith(("VmSize:", "VmData:"))}
    out: list[int | None] = []
    for limit_name, used_name in (("RLIMIT_AS", "VmSize"), ("RLIMIT_DATA", "VmData")):
        soft, _ = resource.getrlimit(getattr(resource, limit_name))
        unlimited = soft == resource.RLIM_INFINITY or used_name not in used
        out.append(None if unlimited else soft - used[used_name])
    return out
