"""Copying a frame's 3D labels to a stretch of frames where nothing moves (``s3k label propagate``).

When the cameras and the object are still for a stretch of frames, the labels of one frame hold for all of
them: each keypoint labelled in two or more views of the source frame is triangulated (unit weights, as the
supervised loss does) and reprojected into every camera of every frame of the stretch, as 2D labels; a view
where the source frame marks the keypoint occluded gets the same mark. The stretch must really be still:
every frame's calibration must equal the source frame's, and in no camera may more than ``max_changed``
percent of its pixels differ from the source frame's by more than ``CHANGE_LEVEL`` grey levels (in any
channel, 0-255). A share of changed pixels, not a mean difference, so that a small object moving in a large
still image is caught, and a video codec's noise of a few grey levels is not. The first frame that breaks
either is named and nothing is written.

Labels people made are never replaced silently: a copy that would change an existing label is refused
unless ``overwrite`` (``--overwrite``), and test frames, whose labels are held out for evaluation, are neither
read nor written unless ``allow_test`` (``--allow-test``). ``dry_run`` (``--dry-run``) computes the same
changes and writes nothing. Every propagation is one batch of the label history, undone with
:func:`undo_propagation` (``s3k label propagate DATASET --undo``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from s3k.base.errors import UserError
from s3k.base.ranges import Range
from s3k.data import Dataset
from s3k.label.solve import triangulate_labels
from s3k.label.store import Edit, LabelStore

__all__ = ["APP_WORDS", "CHANGE_LEVEL", "CLI_WORDS", "DEFAULT_MAX_CHANGED", "PropagateResult",
           "changed_pixels", "describe", "propagate_labels", "undo_propagation"]

CHANGE_LEVEL = 24
"""A pixel has changed when a channel differs by more than this many grey levels (0-255)."""

DEFAULT_MAX_CHANGED = 0.2
"""Largest share of changed pixels, in percent of a camera's image, of a still frame."""
MAX_CHANGED_RANGE = Range(ge=0, le=100)
"""The values ``max_changed`` (``--max-changed``) takes."""

CLI_WORDS = {"frames": "--frames {first}:{last}", "from": "--from {source}", "choose": "choose --frames",
             "max_changed": "--max-changed", "raise": "raise --max-changed", "from_any": "pass --from FRAME",
             "overwrite": "pass --overwrite", "allow_test": "pass --allow-test", "dry_run": "--dry-run"}
"""How a refusal names the options: the command line's flags (``s3k label propagate``)."""
APP_WORDS = {"frames": "frames {first} to {last}", "from": "frame {source} (the one copied)",
             "choose": "choose frames", "max_changed": "'changed pixels at most'", "raise": "raise 'changed "
             "pixels at most'", "from_any": "open a labelled frame and copy from it", "overwrite": "tick "
             "'replace existing labels'", "allow_test": "tick 'include test frames'", "dry_run": "'preview'"}
"""The same in the labelling app's words (its *Propagate to still frames* form)."""


@dataclass
class PropagateResult:
    """What :func:`propagate_labels` wrote (or, with ``dry_run``, would write).

    Attributes:
        source: the frame copied from.
        frames: the frames that change.
        keypoints: the keypoints copied.
        labels: labels written (new and replaced).
        replaced: of those, labels that replace an existing one.
        dry_run: nothing was written.
        per_frame: ``{frame: (new, replaced)}``.
    """

    source: int
    frames: list[int]
    keypoints: list[str]
    labels: int
    replaced: int = 0
    dry_run: bool = False
    per_frame: dict[int, tuple[int, int]] = field(default_factory=dict)


def describe(result: PropagateResult) -> list[str]:
    """What a propagation changes, one line per frame, then the total (for the command's output)."""
    verb = "would copy" if result.dry_run else "copied"
    lines = [f"  frame {f}: {new} new label(s)" + (f", {old} replaced" if old else "")
             for f, (new, old) in sorted(result.per_frame.items())]
    lines.append(f"{verb} frame {result.source}'s {len(result.keypoints)} keypoint(s) "
                 f"({', '.join(result.keypoints)}) to {len(result.frames)} frame(s): {result.labels} labels"
                 + (f", {result.replaced} of them replacing existing labels" if result.replaced else ""))
    return lines


def changed_pixels(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Percent of the pixels of two frames' images ``uint8 (C, H, W, 3)`` that changed (a channel differs by
    more than :data:`CHANGE_LEVEL`), per camera ``(C,)``."""
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=-1)
    return 100.0 * (diff > CHANGE_LEVEL).mean(axis=(1, 2))


def _check_still(ds: Dataset, ids: list[int], source: int, max_changed: float,
                 words: dict[str, str] = CLI_WORDS) -> None:
    """Refuse a frame of ``ids`` whose calibration differs from frame ``source``'s or whose images differ
    from its in more than ``max_changed`` percent of a camera's pixels (checked before anything is
    written); ``words`` name the options in the refusals."""
    ref_cams = ds.calibration([source], np.float64).numpy()
    ref_images = ds.images([source])[0]
    for f in ids:
        if f == source:
            continue
        cams = ds.calibration([f], np.float64).numpy()
        for name in ("K", "dist", "R", "t"):
            a, b = ref_cams[name], cams[name]
            if not np.allclose(a, b, rtol=1e-9, atol=1e-12):
                c = int(np.argmax(np.abs(a - b).reshape(len(ds.cameras), -1).max(axis=1)))
                raise UserError(f"frame {f} is not still: camera {ds.cameras[c]}'s calibration ({name}) "
                                f"differs from frame {source}'s",
                                hint=f"{words['choose']} where the cameras do not move")
        changed = changed_pixels(ref_images, ds.images([f])[0])
        c = int(np.argmax(changed))
        if changed[c] > max_changed:
            raise UserError(f"frame {f} is not still: {changed[c]:.2f}% of camera {ds.cameras[c]}'s pixels "
                            f"differ from frame {source}'s (more than {max_changed:g}%)",
                            hint=f"{words['choose']} where nothing moves, or {words['raise']}")


def _copies(ds: Dataset, store: LabelStore, ids: list[int], source: int, tri: dict[str, np.ndarray]
            ) -> tuple[dict[int, list[Edit]], dict[int, tuple[int, int]], list[tuple[int, str, str]]]:
    """The edits that copy frame ``source``'s triangulated labels ``tri`` onto the frames ``ids``: per frame
    the edits and (new, replaced) counts, and every label an edit would replace."""
    W, H = ds.source_image_size
    i_src = store.row(source)
    edits: dict[int, list[Edit]] = {}
    per_frame: dict[int, tuple[int, int]] = {}
    replaced: list[tuple[int, str, str]] = []
    for f in ids:
        if f == source:
            continue
        i = store.row(f)
        items, n_old = [], 0
        for k, kp in enumerate(ds.keypoints):
            if not tri["valid"][k]:
                continue
            for c, cam in enumerate(ds.cameras):
                if store.present[i_src, c, k] and not store.visible[i_src, c, k]:
                    edit = Edit(cam, kp, visible=False)
                else:
                    u, v = tri["reproj"][c, k]
                    if not (np.isfinite(u) and -0.5 <= u <= W - 0.5 and -0.5 <= v <= H - 0.5):
                        continue
                    edit = Edit(cam, kp, float(u), float(v))
                if store.present[i, c, k]:
                    if _same(edit, store.uv[i, c, k], bool(store.visible[i, c, k])):
                        continue  # already there: no change
                    replaced.append((f, cam, kp))
                    n_old += 1
                items.append(edit)
        if items:
            edits[f] = items
            per_frame[f] = (len(items) - n_old, n_old)
    return edits, per_frame, replaced


def propagate_labels(data: str | Path, first: int, last: int, source: int | None = None,
                     max_changed: float = DEFAULT_MAX_CHANGED, store: LabelStore | None = None,
                     labeller: str | None = None, *, overwrite: bool = False, allow_test: bool = False,
                     dry_run: bool = False, words: dict[str, str] = CLI_WORDS) -> PropagateResult:
    """Copy the 3D labels of frame ``source`` to every frame with an id in ``first..last`` (inclusive).

    Args:
        data: dataset folder.
        first, last: the stretch of frame ids.
        source: the frame whose labels are copied (it need not lie in the stretch); by default the frame of
            the stretch with the most keypoints labelled in two or more views.
        max_changed: largest percentage of changed pixels a still frame may have in any camera.
        store: the dataset's open :class:`LabelStore` (the labelling app passes its own); opened if None.
        labeller: name for the history when the store is opened here.
        overwrite: replace existing labels that differ from the copy (else refused).
        allow_test: read from and write to test frames (else refused).
        dry_run: compute the changes, write nothing.
        words: how refusals name the options (:data:`CLI_WORDS`, the app's :data:`APP_WORDS`).

    Returns:
        A :class:`PropagateResult`.

    Raises:
        UserError: an empty stretch, a source frame without a keypoint labelled in two views, a frame of
            the stretch whose calibration or images differ from the source frame's (named, with the option
            that changes the threshold), a test frame without ``allow_test``, or an existing label that
            would change without ``overwrite``.
    """
    # nan compares false with every percentage: it would let every frame pass as still
    MAX_CHANGED_RANGE.check(max_changed, words["max_changed"], hint="give a percentage from 0 to 100")
    ds = Dataset.open(data, cache="none")
    store = store or LabelStore.open(data, labeller=labeller)
    store.refresh()
    stretch, chosen = words["frames"].format(first=first, last=last), words["from"].format(source=source)
    if last < first:
        raise UserError(f"{stretch}: the last frame comes before the first")
    ids = [int(f) for f in ds.frame_ids if first <= f <= last]
    if not ids:
        raise UserError(f"{stretch}: no frame of {ds.path} has an id in that range")
    tests = [f for f in ids if store.split(f) == "test"]
    if tests and not allow_test:
        raise UserError(f"{stretch}: frame(s) {_listed(tests)} are test frames, whose labels are held out "
                        "for evaluation; nothing was written",
                        hint=f"{words['choose']} without them, or {words['allow_test']} to write them")

    def solved(frame: int) -> dict[str, np.ndarray]:
        uv, mask = store.arrays(frame)
        return triangulate_labels(ds.calibration([frame], np.float64)[0], uv, mask)

    if source is None:
        counts = [(int(solved(f)["valid"].sum()), -i, f) for i, f in enumerate(ids)]
        best = max(counts)
        if best[0] == 0:
            raise UserError(f"{stretch}: no frame there has a keypoint labelled in 2 or more views",
                            hint=f"label one frame first, or {words['from_any']}")
        source = best[2]
    elif source not in store.frames.row_of:
        raise UserError(f"{chosen}: frame {source} is not listed in {ds.path / 'frames.csv'}")
    elif store.split(source) == "test" and not allow_test:
        raise UserError(f"{chosen}: frame {source} is a test frame, whose labels are held out for "
                        "evaluation", hint=f"copy from another frame, or {words['allow_test']}")
    tri = solved(source)
    if not tri["valid"].any():
        raise UserError(f"{words['from'].format(source=source)}: frame {source} has no keypoint labelled in "
                        "2 or more views",
                        hint="label it in a second view first")
    _check_still(ds, ids, source, max_changed, words)
    edits, per_frame, replaced = _copies(ds, store, ids, source, tri)
    keypoints = [kp for k, kp in enumerate(ds.keypoints) if tri["valid"][k]]
    if replaced and not overwrite:
        f, cam, kp = replaced[0]
        frames = sorted({r[0] for r in replaced})
        raise UserError(f"propagating frame {source} would replace {len(replaced)} existing label(s) in "
                        f"frame(s) {_listed(frames)} (first: frame {f}, camera {cam}, keypoint {kp}); "
                        "nothing was written", hint=f"{words['overwrite']} to replace them, or "
                        f"{words['dry_run']} to list the changes")
    if edits and not dry_run:
        store.save_many(edits, None, source=f"propagate from {source}")
    return PropagateResult(int(source), sorted(edits), keypoints, sum(len(e) for e in edits.values()),
                           len(replaced), dry_run, per_frame)


def _same(edit: Edit, uv: np.ndarray, visible: bool) -> bool:
    """The stored label ``(uv, visible)`` is what ``edit`` writes (to a thousandth of a pixel)."""
    if edit.visible != visible:
        return False
    if not edit.visible:
        return True
    return bool(np.all(np.abs(np.asarray([edit.u, edit.v]) - uv) < 1e-3))


def _listed(frames: list[int], most: int = 8) -> str:
    shown = ", ".join(map(str, frames[:most]))
    return shown + (f" and {len(frames) - most} more" if len(frames) > most else "")


def undo_propagation(data: str | Path, store: LabelStore | None = None,
                     labeller: str | None = None) -> tuple[int, list[int]]:
    """Undo the latest propagation of the dataset ``data`` that is not undone yet, from its label history;
    returns ``(source frame, frames restored)``.

    Raises:
        UserError: no propagation to undo, or a frame it wrote was edited since (named).
    """
    store = store or LabelStore.open(data, labeller=labeller)
    store.refresh()
    undone: set[tuple[int, int]] = set()
    for entry in reversed(store.history()):
        key = (entry.get("frame"), entry.get("version"))
        if "undoes" in entry:
            undone.add((entry.get("frame"), entry["undoes"]))
        elif str(entry.get("source", "")).startswith("propagate from") and key not in undone:
            if "batch" not in entry:
                raise UserError(f"the latest propagation in {Path(data) / 'labels-history.jsonl'} was "
                                "written by an older s3k and cannot be undone as one")
            source = int(str(entry["source"]).rsplit(" ", 1)[-1])
            return source, store.undo_batch(entry["batch"], source=f"undo {entry['source']}")
    raise UserError(f"{data}: no propagation to undo in its label history")
