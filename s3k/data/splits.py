"""Which frames of a recording are labelled, test or unlabelled, so that the test frames say how a model does
on a stretch of recording it has not seen labels of (``s3k import --test-frames``).

``blocks`` (the default): the test frames are ``blocks`` contiguous runs of the frames that have labels, at
random places, and no labelled frame lies within ``margin`` frames of a test frame. ``random``: test and
labelled frames drawn at random from the same frames (a test frame is then often a few frames from a labelled
one: the figure says how well a model fills in between its labels). ``last``: one block, the last frames
that have labels, with the labelled frames before it (train on the start of a recording, test on what
follows). ``session``: the whole recording is held out, every frame with labels a test frame and no frame
used for training (``--test-sessions``).
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np

from s3k.base.errors import UserError
from s3k.data.import_choices import DEFAULT_LABELLED

log = logging.getLogger(__name__)

TestFrames = Literal["blocks", "last", "random", "session"]
TEST_FRAMES: tuple[TestFrames, ...] = ("blocks", "last", "random", "session")
DEFAULT_MARGIN = 10
"""Frames kept between the test blocks and the nearest labelled frame when ``--margin`` is not given (less,
said in a note, where the recording is too short for it)."""


def test_blocks(candidates: np.ndarray, n_test: int, blocks: int, rng: np.random.Generator) -> np.ndarray:
    """``n_test`` frames of ``candidates`` (sorted) in ``blocks`` contiguous runs (fewer when ``n_test`` is
    smaller) of near-equal length, with random gaps between them."""
    if n_test == 0:
        return candidates[:0]
    nb = max(1, min(blocks, n_test))
    sizes = np.full(nb, n_test // nb)
    sizes[: n_test % nb] += 1
    gaps = rng.multinomial(len(candidates) - n_test, np.full(nb + 1, 1.0 / (nb + 1)))
    picked, start = [], 0
    for gap, size in zip(gaps, sizes):
        start += gap
        picked.append(candidates[start:start + size])
        start += size
    return np.concatenate(picked)


def distances_to(frames: np.ndarray, marks: np.ndarray) -> np.ndarray:
    """Frames from each of ``frames`` to the nearest of ``marks`` (inf when there is none)."""
    if not len(marks):
        return np.full(len(frames), np.inf)
    marks = np.sort(marks)
    pos = np.searchsorted(marks, frames)
    before = np.abs(frames - marks[np.clip(pos - 1, 0, len(marks) - 1)])
    after = np.abs(marks[np.clip(pos, 0, len(marks) - 1)] - frames)
    return np.minimum(before, after).astype(np.float64)


def held_out_split(candidates: np.ndarray, all_frames: np.ndarray, n_labelled: int | str, n_test: int,
                   seed: int, stride: int, margin: int | None = None, blocks: int = 1,
                   fewer_ok: bool = False, last: bool = False) -> dict[int, str]:
    """Test frames in ``blocks`` contiguous runs of ``candidates`` (the frames that have labels), or with
    ``last`` in one run at their end; labelled frames (a count, or ``"all"``) at random among the candidates
    more than ``margin`` frames from every test frame; every ``stride``-th other frame unlabelled.

    ``margin`` None: :data:`DEFAULT_MARGIN`, or the largest smaller margin that leaves ``n_labelled`` frames
    (with ``"all"``: :data:`~s3k.data.import_choices.DEFAULT_LABELLED` of them), said in a note.
    ``fewer_ok``: take the frames there are when fewer than ``n_labelled`` are far enough (a default
    count); otherwise that is refused, naming the options that help."""
    candidates = np.sort(np.asarray(candidates, dtype=np.int64))
    if n_test < 0:
        raise UserError(f"--test must be >= 0, got {n_test}")
    if n_test > len(candidates):
        raise UserError(f"--test {n_test}: only {len(candidates)} frames have a keypoint labelled in >= 2 "
                        "views")
    rng = np.random.default_rng(seed)
    test = candidates[len(candidates) - n_test:] if last else test_blocks(candidates, n_test, blocks, rng)
    rest = np.setdiff1d(candidates, test)
    far = distances_to(rest, test)
    every = str(n_labelled) == "all"
    want = int(n_labelled) if not every else len(rest) if margin is None else 0
    want = min(want, DEFAULT_LABELLED, len(rest)) if every else want  # "all": what lies beyond the margin
    tried = [margin] if margin is not None else list(range(DEFAULT_MARGIN, -1, -1))
    for m in tried:
        eligible = rest[far > m]
        if len(eligible) >= want:
            break
    else:
        if not fewer_ok:
            raise UserError(
                f"--labelled {want}: only {len(eligible)} frames with labels lie more than {m} frames from "
                f"the {n_test} test frames (in {max(1, min(blocks, n_test))} block(s))",
                hint="lower --labelled, --test or --margin, or pass --test-frames random")
    if margin is None and m < DEFAULT_MARGIN and n_test:
        log.info(f"note: the labelled frames are kept {m + 1} or more frames from the test frames (the "
                 f"recording is too short for the default margin of {DEFAULT_MARGIN}; --margin sets it)")
    labelled = eligible if every else rng.permutation(eligible)[:want]
    splits = {int(f): "unlabelled" for f in all_frames if f % stride == 0}
    splits.update({int(f): "test" for f in test})
    splits.update({int(f): "labelled" for f in labelled})
    return dict(sorted(splits.items()))


def session_split(candidates: np.ndarray) -> dict[int, str]:
    """A held-out session: every frame with labels a test frame, nothing to train on."""
    return {int(f): "test" for f in np.sort(candidates)}
