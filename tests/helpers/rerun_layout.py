"""The layout (blueprint) a ``.rrd`` file opens on, read back with Rerun's own reader (``rerun.chunk``), and
the same read from a ``rerun.blueprint.Blueprint`` object, so that a test can check which views a recording
opens with and what each shows."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def _first(values: list) -> Any:
    value = values[-1] if values else None
    return value[0] if isinstance(value, list) and len(value) == 1 else value


def _listed(value: Any) -> list:
    return [] if value is None else [value] if isinstance(value, str) else list(value)


def file_views(path: str | Path) -> list[dict[str, Any]]:
    """Each view of the file's blueprint: ``kind`` (``"2D"``, ``"3D"``, ``"TimeSeries"``...), ``name``,
    ``origin``, ``query`` (its contents' expressions) and, for a 3D view, ``eye`` (``{position, look_target,
    eye_up}``); ``[]`` where the file holds no blueprint."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    stores = reader.blueprints()
    if not stores:
        return []
    parts: dict[str, dict[str, Any]] = {}
    for chunk in reader.stream(store=stores[-1]):
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if ":" in name:
                value = _first(batch.column(name).to_pylist())
                parts.setdefault(chunk.entity_path, {})[name.split(":")[1]] = value
    views = []
    for path_, fields in parts.items():
        if "class_identifier" not in fields:
            continue
        eye = parts.get(f"{path_}/EyeControls3D")
        views.append({"kind": fields["class_identifier"], "name": fields.get("display_name"),
                      "origin": "/" + str(fields.get("space_origin", "/")).strip("/"),
                      "query": _listed(parts.get(f"{path_}/ViewContents", {}).get("query")),
                      "eye": eye and {k: eye.get(k) for k in ("position", "look_target", "eye_up")}})
    return views


def blueprint_views(blueprint: Any) -> list[Any]:
    """The views (``rerun.blueprint.View``) of a ``Blueprint`` object, depth first."""
    out, todo = [], [blueprint.root_container]
    while todo:
        part = todo.pop(0)
        if hasattr(part, "class_identifier"):
            out.append(part)
        else:
            todo = list(part.contents) + todo
    return out
