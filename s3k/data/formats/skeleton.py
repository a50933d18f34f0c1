"""A skeleton (edges between keypoints, for drawing) from the files other tools keep it in:
:func:`read_skeleton`, and where an importer finds it beside the labels (:func:`dlc_project_config`,
:func:`anipose_project_config`); :func:`write_dlc_config` writes DeepLabCut's ``config.yaml``.

- SLEAP: a project's (``.slp``) skeleton edges (read with sleap-io), an analysis file's ``edge_names``.
- DeepLabCut: the project's ``config.yaml`` ``skeleton`` (a list of ``[bodypart, bodypart]`` pairs).
- anipose: the project's ``config.toml`` ``[labeling] scheme`` (a list of chains ``[a, b, c]``, each drawn as
  the edges a-b, b-c).
- s3k: a dataset folder or its ``s3k.json`` ``skeleton``.

Edges are ``(keypoint, keypoint)`` name pairs, each given once, in the file's order.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path
from s3k.data.formats.labels2d import unique_edges
from s3k.data.formats.slp import load_slp
from s3k.data.hdf5 import open_hdf5

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

Edge = tuple[str, str]

__all__ = ["Edge", "anipose_project_config", "check_edges", "dlc_project_config", "read_skeleton",
           "unique_edges", "write_dlc_config"]

SOURCES = ("a SLEAP .slp or analysis .h5, a DeepLabCut config.yaml, an anipose config.toml or an s3k dataset "
           "folder")


def check_edges(edges: Sequence[Edge], keypoints: Sequence[str], source: str) -> list[Edge]:
    """``edges`` when every name is one of ``keypoints``; else a UserError naming ``source`` and the name."""
    for a, b in edges:
        for name in (a, b):
            if name not in keypoints:
                raise UserError(f"{source}: skeleton edge {a}-{b} names {name!r}, which is not a keypoint "
                                f"({', '.join(keypoints)})", hint="give a skeleton of these keypoints with "
                                "--skeleton FILE")
    return list(edges)


def _chains(value: Any, where: str) -> list[Edge]:
    """anipose's scheme (chains) or DLC's skeleton (pairs): consecutive names of each list are edges."""
    if not isinstance(value, list) or not all(
            isinstance(chain, list) and len(chain) >= 2 and all(isinstance(n, str) for n in chain)
            for chain in value):
        raise UserError(f"{where}: expected a list of lists of keypoint names, got {str(value)[:80]}")
    return unique_edges((chain[i], chain[i + 1]) for chain in value for i in range(len(chain) - 1))


def _slp_edges(path: Path) -> list[Edge]:
    """The edges of a SLEAP project's one skeleton (a project with several is refused)."""
    skeletons = list(load_slp(path).skeletons)
    if len(skeletons) != 1:
        raise UserError(f"{path}: {len(skeletons)} skeletons; s3k reads projects with one skeleton")
    return unique_edges(skeletons[0].edge_names)


def analysis_edges(h5: Any, path: Path | str) -> list[Edge]:
    """The ``edge_names`` of an open SLEAP analysis file (``[]`` where it has none)."""
    if "edge_names" not in h5:
        return []
    raw = np.asarray(h5["edge_names"][()])
    if raw.size == 0:
        return []
    if raw.ndim != 2 or raw.shape[1] != 2:
        raise UserError(f"{path}: 'edge_names' has shape {raw.shape}, expected (edges, 2)")
    try:
        names = [[v.decode() if isinstance(v, bytes) else str(v) for v in row] for row in raw]
    except UnicodeDecodeError:
        raise UserError(f"{path}: 'edge_names' holds a name that is not UTF-8 text") from None
    return unique_edges(names)


def _yaml(path: Path) -> Any:
    try:
        import yaml
    except ImportError as exc:  # pragma: no cover - installed with s3k's "formats" extra
        raise UserError(f"{path}: reading DeepLabCut's config.yaml needs PyYAML ({exc})",
                        hint="pip install 's3k[formats]'") from exc
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not readable YAML ({str(exc).splitlines()[0]})") from None


def read_skeleton(path: str | Path) -> list[Edge]:
    """The skeleton edges of ``path`` (module docstring); ``[]`` when the file gives none.

    Raises:
        UserError: a file that is none of those, or whose skeleton is malformed (naming the file and field).
    """
    path = Path(path)
    if path.is_dir() and (path / "s3k.json").is_file():
        path = path / "s3k.json"
    if not path.is_file():
        raise UserError(f"--skeleton {path}: no such file", hint=f"give {SOURCES}")
    suffix = path.suffix.lower()
    if suffix == ".slp":
        return _slp_edges(path)
    if suffix in (".h5", ".hdf5"):

        with open_hdf5(path, "HDF5 (SLEAP analysis file)") as h5:
            return analysis_edges(h5, path)
    if suffix in (".yaml", ".yml"):
        doc = _yaml(path)
        if not isinstance(doc, dict):
            raise UserError(f"{path}: not a DeepLabCut config.yaml (no mapping at the top)")
        value = doc.get("skeleton") or []
        return _chains(value, f"{path}: skeleton") if value else []
    if suffix == ".toml":
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: not readable TOML ({exc})") from None
        labeling = doc.get("labeling")
        value = labeling.get("scheme") if isinstance(labeling, dict) else None
        return _chains(value, f"{path}: [labeling] scheme") if value else []
    if suffix == ".json":
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: not readable JSON ({exc})") from None
        value = doc.get("skeleton") if isinstance(doc, dict) else None
        return _chains(value, f"{path}: skeleton") if value else []
    raise UserError(f"--skeleton {path}: not a skeleton file", hint=f"give {SOURCES}")


def dlc_project_config(csv_path: str | Path) -> Path | None:
    """A DeepLabCut project's ``config.yaml`` for a label CSV in its layout
    (``PROJECT/labeled-data/VIDEO/CollectedData_*.csv``), or None."""
    folder = Path(csv_path).resolve().parent
    if folder.parent.name != "labeled-data":
        return None
    config = folder.parent.parent / "config.yaml"
    return config if config.is_file() else None


def anipose_project_config(calibration: str | Path) -> Path | None:
    """anipose's ``config.toml`` beside a ``calibration.toml`` or in one of the three folders above it (a
    project keeps it at the top, a session's calibration in ``SESSION/calibration/``; the same folders as the
    board's unit is looked for in), when it has a ``[labeling] scheme``."""
    start = Path(calibration).resolve()
    folder = start if start.is_dir() else start.parent
    for candidate in [folder, *folder.parents][:4]:
        config = candidate / "config.toml"
        if config.is_file() and config != start:
            try:
                doc = tomllib.loads(config.read_text(encoding="utf-8"))
            except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
                continue
            if isinstance(doc.get("labeling"), dict) and doc["labeling"].get("scheme"):
                return config
    return None


def write_dlc_config(path: str | Path, keypoints: Sequence[str], skeleton: Sequence[Edge], scorer: str,
                     videos: Sequence[str], task: str) -> Path:
    """Write a DeepLabCut project's ``config.yaml`` with the keys its label readers use: ``Task``,
    ``scorer``, ``project_path``, ``video_sets``, ``bodyparts``, ``skeleton`` (pairs) and the drawing
    defaults."""

    try:
        import yaml
    except ImportError as exc:  # pragma: no cover - installed with s3k's "formats" extra
        raise UserError(f"{path}: writing DeepLabCut's config.yaml needs PyYAML ({exc})",
                        hint="pip install 's3k[formats]'") from exc
    path = Path(path)
    doc = {
        "Task": task, "scorer": scorer, "date": "", "multianimalproject": False,
        "project_path": str(path.resolve().parent),
        "video_sets": {v: {"crop": ""} for v in videos},
        "bodyparts": list(keypoints),
        "skeleton": [[a, b] for a, b in skeleton],
        "skeleton_color": "black", "pcutoff": 0.6, "dotsize": 12, "alphavalue": 0.7, "colormap": "rainbow",
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path
