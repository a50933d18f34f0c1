"""The dataset's skeleton as the labelling app edits it: edges between keypoints, kept in ``s3k.json``.

An edge is a pair of keypoint names, without direction (``[a, b]`` and ``[b, a]`` are the same edge). Each
change rewrites ``s3k.json`` atomically (:func:`s3k.base.fileio.atomic_write_text`: a crash leaves the old
file or the new one) under the dataset's label lock, from the file as it is on disk, so every other field of
it is kept as it was.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_text, file_lock, read_text
from s3k.data.tables import METADATA_FILE
from s3k.label.store import LOCK_FILE

__all__ = ["edit_skeleton"]


def _edge(pair: Sequence[str] | None, keypoints: list[str], what: str) -> tuple[str, str] | None:
    if pair is None:
        return None
    if len(pair) != 2:
        raise UserError(f"skeleton {what}: an edge is two keypoint names, got {list(pair)!r}")
    for name in pair:
        if name not in keypoints:
            raise UserError(f"skeleton {what}: unknown keypoint {name!r}; the dataset's keypoints are "
                            f"{keypoints}")
    if pair[0] == pair[1]:
        raise UserError(f"skeleton {what}: an edge joins two different keypoints, got {pair[0]!r} twice")
    return pair[0], pair[1]


def edit_skeleton(root: str | Path, keypoints: list[str], add: Sequence[str] | None = None,
                  remove: Sequence[str] | None = None) -> list[tuple[str, str]]:
    """Add the edge ``add`` and/or remove the edge ``remove`` (keypoint name pairs) of the skeleton of the
    dataset ``root``, written to its ``s3k.json`` before returning; returns the skeleton after the change.

    Raises:
        UserError: an unknown keypoint, an edge from a keypoint to itself, adding an edge the skeleton
            has, or removing one it has not (named).
    """
    new, old = _edge(add, keypoints, "add"), _edge(remove, keypoints, "remove")
    path = Path(root) / METADATA_FILE
    with file_lock(Path(root) / LOCK_FILE):
        meta = json.loads(read_text(path))
        edges = [(str(a), str(b)) for a, b in meta.get("skeleton", [])]
        if old is not None:
            kept = [e for e in edges if set(e) != set(old)]
            if len(kept) == len(edges):
                raise UserError(f"skeleton: no edge {old[0]} - {old[1]} to remove in {path}")
            edges = kept
        if new is not None:
            if any(set(e) == set(new) for e in edges):
                raise UserError(f"skeleton: the edge {new[0]} - {new[1]} is already in {path}")
            edges.append(new)
        meta["skeleton"] = [list(e) for e in edges]
        text = json.dumps(meta, indent=2)  # lists of scalars on one line, as the dataset writer has them
        text = re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text)
        atomic_write_text(text + "\n", path)
    return edges
