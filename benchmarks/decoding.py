"""Sharper heatmap decodings, read on trained detectors: the same networks, the 2D detection taken other ways.

Every read-out takes a view's detection as its heatmap's mean within a window around the peak
(:func:`s3k.readout.window_cells`: six target widths, 6 cells each side for the refining pass's target of one
cell). A mean over a window is pulled towards whichever side of the peak holds more probability. Each RUN is
read on DATA's ``--split`` (both passes of a two-pass run alike) with:

- ``default``: the trained read-out;
- ``window N``: the mean within N cells of the peak (``--windows``);
- ``log-parabola``: the peak cell moved by the vertex of the parabola through the log-probabilities of it and
  its two neighbours along each axis (the exact mode of a Gaussian peak; at most half a cell; a peak on the
  heatmap's edge keeps its cell centre). It is not an option of s3k: this benchmark swaps it in for the
  window mean of :func:`s3k.readout.views.moments` while it reads.

Printed and written per run and way: median and RMS 3D error and the share within 10 mm (``s3k evaluate``'s
metrics). Nothing is trained.

    python benchmarks/decoding.py RUN DATA [RUN DATA ...] [--windows 1,2,3] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import os
import sys
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import add_run_data_arguments, run_data_pairs, split_store, write_runs  # noqa: E402

FIGURES = ("median_mm", "rms_mm", "pck_10mm")


def log_parabola(probs: torch.Tensor, stride: int, radius: int,
                 peak: torch.Tensor | None = None) -> torch.Tensor:
    """Each heatmap's peak cell moved by the vertex of the parabola through its log-probabilities and its two
    neighbours', per axis, at most half a cell (``radius`` is not used: the fit reads three cells per axis);
    image pixels ``(*, 2)``, as :func:`s3k.readout.heatmaps.peak_window_mean` returns."""
    from s3k.readout.heatmaps import cell_centres

    h, w = probs.shape[-2:]
    lead = probs.shape[:-2]
    flat = probs.reshape(-1, h * w)
    peak = flat.argmax(-1) if peak is None else peak.reshape(-1)
    row, col = torch.div(peak, w, rounding_mode="floor"), peak % w
    logp = flat.clamp_min(torch.finfo(flat.dtype).tiny).log()

    def at(r: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return logp.gather(1, (r.clamp(0, h - 1) * w + c.clamp(0, w - 1))[:, None])[:, 0]

    centre = at(row, col)

    def vertex(before: torch.Tensor, after: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
        curve = before - 2 * centre + after  # < 0 at a peak
        shift = 0.5 * (before - after) / torch.where(curve < 0, curve, torch.full_like(curve, -1.0))
        return torch.where(inside & (curve < 0), shift.clamp(-0.5, 0.5), torch.zeros_like(shift))

    du = vertex(at(row, col - 1), at(row, col + 1), (col > 0) & (col < w - 1))
    dv = vertex(at(row - 1, col), at(row + 1, col), (row > 0) & (row < h - 1))
    cu, cv = cell_centres(h, w, stride, device=probs.device, dtype=probs.dtype)
    return torch.stack((cu[col] + du * stride, cv[row] + dv * stride), dim=-1).reshape(*lead, 2)


@contextmanager
def decoded_by(function):
    """The read-out's window mean replaced by ``function`` while inside (None: left as it is)."""
    from s3k.readout import views

    kept = views.peak_window_mean
    if function is not None:
        views.peak_window_mean = function
    try:
        yield
    finally:
        views.peak_window_mean = kept


def passes(detector) -> list:
    """The one-pass detectors a detector reads with: a two-pass detector's coarse and refining pass."""
    return [detector.coarse, detector.fine] if hasattr(detector, "fine") else [detector]


def read(run: Path, data: Path, split: str, windows: list[int]) -> dict:
    """The ways of decoding ``run``'s heatmaps on ``data``'s ``split``."""
    from s3k.detector import Detector
    from s3k.inference.evaluate import evaluate_store
    from s3k.readout import window_cells

    ds, store = split_store(data, split)
    detector = Detector.load(run, "cpu")
    trained = [(p, p.readout) for p in passes(detector)]
    out: dict = {"default_window_cells": [window_cells(p.meta.sigma, p.meta.stride, r.window)
                                          for p, r in trained]}
    ways = [("default", None, None), *((f"window {n}", n, None) for n in windows),
            ("log-parabola", 1, log_parabola)]
    for name, window, function in ways:
        for p, readout in trained:
            p.readout = readout if window is None else replace(readout, window=window)
        with decoded_by(function):
            metrics, _ = evaluate_store(detector, store, units=ds.units)
        out[name] = {k: metrics[k] for k in FIGURES}
        print(f"{run} {name}: median {metrics['median_mm']:.3f} mm, RMS {metrics['rms_mm']:.3f} mm, "
              f"within 10 mm {100 * metrics['pck_10mm']:.1f}%", flush=True)
    for p, readout in trained:
        p.readout = readout
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_data_arguments(p)
    p.add_argument("--windows", default="1,2,3", help="window half-sides to read with, cells (default 1,2,3)")
    a = p.parse_args(argv)
    windows = [int(n) for n in a.windows.split(",") if n]
    if any(n < 1 for n in windows):
        p.error(f"--windows {a.windows}: each at least 1 cell")
    torch.set_num_threads(1)
    runs = {run: read(Path(run), Path(data), a.split, windows) for run, data in run_data_pairs(p, a)}
    write_runs("benchmarks/decoding.py", argv, a, runs)


if __name__ == "__main__":
    main()
