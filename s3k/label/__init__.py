"""Labelling in the browser (``s3k label``): click a keypoint in two views, s3k triangulates the rest.

Modules, one job each:

- :mod:`~s3k.label.store`: ``LabelStore``, the dataset's labels as the app edits them (each save on disk at
  once, versioned per frame, logged in ``labels-history.jsonl``).
- :mod:`~s3k.label.solve`: the geometry the app shows (triangulation, reprojections, residuals, epipolar
  curves) with s3k's cameras and read-out.
- :mod:`~s3k.label.propagate`: ``propagate_labels``, one frame's 3D labels copied to a still stretch.
- :mod:`~s3k.label.suggest`: a trained run's suggestions and its ranking of frames by multi-view doubt.
- :mod:`~s3k.label.skeleton`: ``edit_skeleton``, the dataset's skeleton edges edited in ``s3k.json``.
- :mod:`~s3k.label.server`: the FastAPI app and ``serve``; the page itself is ``static/``.

The web modules import FastAPI; the others do not, so ``propagate_labels`` works without it.
"""

from s3k.label.propagate import PropagateResult, propagate_labels
from s3k.label.store import Edit, LabelStore, StaleVersion

__all__ = ["Edit", "LabelStore", "PropagateResult", "StaleVersion", "propagate_labels"]
