"""What a sweep reports: ``summary.json``, the figures and the ``README.md`` page of an experiment folder.

:func:`summarize` rebuilds all three from the runs' ``result.json`` files (``--summarize-only``);
:func:`resummarize` from the grid points of an existing ``summary.json`` when the run folders are gone (e.g.
the published ``docs/results/NAME``); :func:`publish` copies them to a results folder. Errors are compared in
millimetres: 3D errors as measured, per-view pixel errors times the scene's pixel size at the workspace centre
(:func:`s3k.sim.generate.scene_mm_per_px`), the paper's pixel figures times :data:`PAPER_MM_PER_PX`.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

import s3k
from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json, atomic_write_text
from s3k.experiments.findings import (
    add_mm,
    aggregate,
    findings,
    fmt,
    mean_std,
    paper_mm,
    param_values,
    verdict,
)
from s3k.experiments.grid import (
    DESCRIPTIONS,
    EXPERIMENT_SCENES,
    PAPER_CATEGORY_TEST_PX,
    PAPER_MM_PER_PX,
    PAPER_SIZE,
    PAPER_STEPS,
    RESULT_FILE,
    SUMMARY_FILE,
)

#: What a summary says about the runs it summarizes (kept as they are when it is re-summarized).
_RUN_FIELDS = ("runs", "scales", "image_sizes", "steps", "two_pass", "commands", "code_revisions",
               "runs_without_provenance")

#: Sections of README.md that :func:`readme` writes; any other ``## `` section after them is kept.
_GENERATED_SECTIONS = ("## Findings", "## Figures")


def source_revision() -> str | None:
    """The git commit of the s3k source in use (``-dirty`` when its files differ from it), or None when s3k
    is not run from a git checkout or git is unavailable."""
    pkg = Path(s3k.__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "-C", str(pkg), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10)
        if rev.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(pkg), "status", "--porcelain", "--untracked-files=no", "--",
                                "."], capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return rev.stdout.strip() + ("-dirty" if dirty else "")


def load_results(exp_dir: Path) -> list[dict[str, Any]]:
    """Every ``result.json`` under ``exp_dir/runs``, sorted by run name."""
    return [json.loads(path.read_text()) for path in sorted((exp_dir / "runs").glob(f"*/{RESULT_FILE}"))]


def scene_pixel_sizes(experiment: str, sizes: Sequence[int]) -> dict[int, float]:
    """Millimetres per pixel at the workspace centre of ``experiment``'s scene, per image size."""
    from s3k.sim.generate import scene_mm_per_px

    scene = EXPERIMENT_SCENES.get(experiment)
    return {int(s): scene_mm_per_px(scene, int(s)) for s in sizes} if scene else {}


def run_pixel_sizes(experiment: str, results: Sequence[dict[str, Any]]) -> dict[int, float]:
    """Millimetres per pixel of the images the runs' networks saw, per image size: the scene's at the
    workspace centre for one-pass runs; for two-pass runs (whose pixel errors are in crop pixels) the crops'
    at the object as their evaluation measured it (``mm_per_px``), the mean over the runs of that size."""
    one_pass = sorted({r["image_size"][0] for r in results if not r.get("two_pass")})
    sizes = scene_pixel_sizes(experiment, one_pass)
    crops: dict[int, list[float]] = {}
    for r in results:
        if r.get("two_pass") and r["metrics"]["test"].get("mm_per_px"):
            crops.setdefault(int(r["image_size"][0]), []).append(float(r["metrics"]["test"]["mm_per_px"]))
    sizes.update({s: float(np.mean(v)) for s, v in crops.items()})
    return sizes


def summarize(exp_dir: Path, experiment: str | None = None) -> dict[str, Any]:
    """Write ``summary.json``, the plots and ``README.md`` of one experiment folder from its runs' JSON."""
    exp_dir = Path(exp_dir)
    experiment = experiment or exp_dir.name
    results = load_results(exp_dir)
    sizes = sorted({r["image_size"][0] for r in results})
    mm_per_px = run_pixel_sizes(experiment, results)
    runs = {
        "runs": len(results), "scales": sorted({r.get("scale", "?") for r in results}), "image_sizes": sizes,
        "steps": sorted({r["config"]["steps"] for r in results}),
        "two_pass": [json.loads(t) for t in sorted({json.dumps(r["two_pass"], sort_keys=True)
                                                    for r in results if r.get("two_pass")})],
        # provenance as the runs recorded it (runs made before it was recorded count as unrecorded)
        "commands": sorted({r["command"] for r in results if r.get("command")}),
        "code_revisions": sorted({r["code_revision"] for r in results if r.get("code_revision")}),
        "runs_without_provenance": sum(1 for r in results if not r.get("command")),
    }
    return _write(exp_dir, experiment, aggregate(results, mm_per_px), mm_per_px, runs)


def resummarize(exp_dir: Path, experiment: str | None = None) -> dict[str, Any]:
    """Rewrite ``summary.json``, the plots and ``README.md`` of a folder from its ``summary.json`` alone.

    For results whose run folders are not kept: the grid points (statistics over seeds per metric) are taken
    as they are, given the millimetre errors of this revision (:func:`add_mm`; a summary written before
    they existed loads too), and the findings, figures and page are made again. What the summary says about
    the runs (count, scale, commands, revisions) is kept, and ``resummarized_from`` records which summary of
    the runs this came from.

    Raises:
        UserError: ``experiment`` is given and the summary is of another experiment.
    """
    exp_dir = Path(exp_dir)
    old = json.loads((exp_dir / SUMMARY_FILE).read_text())
    if experiment is not None and old["experiment"] != experiment:
        raise UserError(f"{exp_dir / SUMMARY_FILE}: a summary of experiment {old['experiment']!r}, not "
                        f"{experiment!r}", hint="check NAME and --out")
    experiment = old["experiment"]
    if old.get("two_pass"):  # the crops' pixel sizes were measured by the runs' evaluations: kept
        mm_per_px = {int(k): float(v) for k, v in old["mm_per_px"].items()}
    else:
        mm_per_px = scene_pixel_sizes(experiment, old["image_sizes"])
    points = [add_mm(p, mm_per_px) for p in old["points"]]
    runs = {k: old.get(k, 0 if k in ("runs", "runs_without_provenance") else []) for k in _RUN_FIELDS}
    source = old.get("resummarized_from") or {k: old[k] for k in ("generated_at", "summary_revision")
                                              if old.get(k) is not None}
    return _write(exp_dir, experiment, points, mm_per_px, runs, resummarized_from=source)


def _write(exp_dir: Path, experiment: str, points: list[dict[str, Any]], mm_per_px: Mapping[int, float],
           runs: dict[str, Any], resummarized_from: dict[str, Any] | None = None) -> dict[str, Any]:
    """The summary of ``points``, written with its figures and page (keeping hand-written page sections)."""
    summary: dict[str, Any] = {
        "experiment": experiment, "description": DESCRIPTIONS.get(experiment, ""),
        **{k: runs[k] for k in ("runs", "scales", "image_sizes", "steps", "two_pass")},
        "paper": {"image_size": PAPER_SIZE, "steps": PAPER_STEPS, "mm_per_px": PAPER_MM_PER_PX},
        "mm_per_px": {str(s): v for s, v in sorted(mm_per_px.items())},
        "mm_per_px_source": (
            "two passes: the crop's pixel at the object (the crop cameras' workspace centre) as s3k evaluate "
            "measures it, mean over the runs" if runs["two_pass"] else
            f"s3k.sim.generate.scene_mm_per_px({EXPERIMENT_SCENES.get(experiment)!r}, size): median over the "
            "cameras of 200 frames drawn as s3k simulate draws them of the size of one pixel at the point "
            "nearest to the cameras' optical axes"),
        "error_metric": "rms_mm_2d: rms_px x mm_per_px at the run's image size (the per-view 2D error at the "
                        "workspace centre, mm on the object)",
        "points": points, "findings": findings(experiment, points),
        "generated_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "summary_revision": source_revision(),
        **{k: runs[k] for k in ("commands", "code_revisions", "runs_without_provenance")},
    }
    if resummarized_from is not None:
        summary["resummarized_from"] = resummarized_from
    if experiment == "category":
        summary["paper"]["category_test_px"] = {str(k): v for k, v in PAPER_CATEGORY_TEST_PX.items()}
    figures = plot(experiment, points, exp_dir, mm_per_px)
    summary["figures"] = [p.name for p in figures]
    notes = _notes(exp_dir / "README.md")
    atomic_write_json(summary, exp_dir / SUMMARY_FILE)
    atomic_write_text(readme(summary) + notes, exp_dir / "README.md")
    return summary


def _notes(page: Path) -> str:
    """The hand-written sections of an existing page: from its first ``## `` heading that :func:`readme` does
    not write to the end ("" when there is no page or none)."""
    if not page.is_file():
        return ""
    lines = page.read_text().splitlines(keepends=True)
    for i, line in enumerate(lines):
        if line.startswith("## ") and line.strip() not in _GENERATED_SECTIONS:
            return "\n" + "".join(lines[i:])
    return ""


def _series(points, split: str, metric: str, x_key: str, **where) -> tuple[list, list, list]:
    xs, ys, es = [], [], []
    for p in points:
        if split not in p or not all(p["params"].get(k) == v for k, v in where.items()):
            continue
        s = p[split][metric]
        if s["mean"] is None:
            continue
        xs.append(p["params"][x_key])
        ys.append(s["mean"])
        es.append(s["std"] or 0.0)
    order = np.argsort(xs)
    return [xs[i] for i in order], [ys[i] for i in order], [es[i] for i in order]


def _finish(ax, xlabel: str, log: bool = True) -> None:
    """The x axis (log scale unless ``log`` is False) and legend of a panel of curves."""
    if log:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.legend(fontsize=8)


_PANELS = (("rms_mm_2d", "per-view RMS error (mm at the workspace centre)"),
           ("median_mm", "median 3D error (mm)"))


def plot(experiment: str, points: list[dict[str, Any]], out_dir: Path,
         mm_per_px: Mapping[int, float] | None = None) -> list[Path]:
    """Write the experiment's figures (PNG) to ``out_dir``; returns their paths.

    ``mm_per_px`` (per image size) is only named in the caption.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    written: list[Path] = []
    sizes = sorted({p["image_size"][0] for p in points})
    steps = sorted({p["steps"] for p in points})
    pixels = "/".join(fmt((mm_per_px or {}).get(s)) for s in sizes)
    scale_note = (f"{'/'.join(map(str, sizes))} px ({pixels} mm per pixel), {'/'.join(map(str, steps))} "
                  f"steps (paper: {PAPER_SIZE} px, {PAPER_MM_PER_PX} mm per pixel, {PAPER_STEPS // 1000}k "
                  "batches); bars: std over seeds")

    def figure(name: str, draw: Callable[[Any, str, str], None], title: str, panels=_PANELS) -> None:
        fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4))
        axes = np.atleast_1d(axes)
        for ax, (metric, label) in zip(axes, panels):
            if points:
                draw(ax, metric, label)
            else:
                ax.text(0.5, 0.5, "no finished runs", ha="center", va="center", transform=ax.transAxes)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        fig.suptitle(f"{title}\n{scale_note}", fontsize=9)
        fig.tight_layout()
        path = out_dir / f"{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    def values(key: str) -> list:
        return param_values(points, key)

    if experiment == "label-efficiency":
        def per_labelled(ax, metric, label):
            for U in values("unlabelled"):
                x, y, e = _series(points, "test", metric, "labelled", unlabelled=U)
                ax.errorbar(x, y, yerr=e, marker="o", capsize=3,
                            label="labels only (no_unsup)" if U == 0 else f"S3K, {U} unlabelled")
            _finish(ax, "labelled frames")

        figure("error_vs_labelled", per_labelled, "Box: test error per labelled count, one curve per "
               "unlabelled count (paper fig. 4 left)")

        def per_total(ax, metric, label):
            xs, ys, cs = [], [], []
            for p in points:
                s = p["test"][metric] if "test" in p else {"mean": None}
                if s["mean"] is None:
                    continue
                L, U = p["params"]["labelled"], p["params"]["unlabelled"]
                xs.append(L + U)
                ys.append(s["mean"])
                cs.append(L / (L + U))
            sc = ax.scatter(xs, ys, c=cs, cmap="viridis", norm=matplotlib.colors.LogNorm(vmin=1e-3, vmax=1),
                            s=40, edgecolors="k", linewidths=0.4)
            plt.colorbar(sc, ax=ax, label="labelled share L / (L + U)")
            ax.set_xscale("log")
            ax.set_xlabel("total training frames L + U")

        figure("error_vs_total_frames", per_total, "Box: test error against total frames, coloured by the "
               "labelled share (paper fig. 4 right)")
    elif experiment == "domain-shift":
        def per_mode(ax, metric, label):
            for i, U in enumerate(values("unlabelled")):
                for mode, style in (("start", "-"), ("full", "--")):
                    x, y, e = _series(points, "test", metric, "labelled", mode=mode, unlabelled=U)
                    if x:
                        ax.errorbar(x, y, yerr=e, marker="o", capsize=3, linestyle=style, color=f"C{i}",
                                    label=f"{mode}, " + ("labels only" if U == 0 else f"S3K {U} unlabelled"))
            _finish(ax, "labelled frames")

        figure("error_vs_labelled", per_mode, "Distractors: test error on unseen distractor sets; labels "
               "from the first set (start, solid) or all (full, dashed)")
    elif experiment == "category":
        def per_instances(ax, metric, label):
            for split, style in (("train", "--"), ("test", "-")):
                x, y, e = _series(points, split, metric, "instances")
                ax.errorbar(x, y, yerr=e, marker="o", capsize=3, linestyle=style,
                            label=f"{'training' if split == 'train' else 'held-out'} instances")
            if metric == "rms_mm_2d":
                n = sorted(PAPER_CATEGORY_TEST_PX)
                ax.plot(n, [paper_mm(PAPER_CATEGORY_TEST_PX[k]) for k in n], "k:", marker="s",
                        label=f"paper, held-out (400 px, {PAPER_MM_PER_PX} mm per pixel)")
            _finish(ax, "training instances", log=False)

        figure("error_vs_instances", per_instances, "Category: error on training and held-out instances "
               "(paper sec. 4.3 table)")
    elif experiment == "alpha":
        def per_alpha(ax, metric, label):
            for L in values("labelled"):
                x, y, e = _series(points, "test", metric, "alpha", labelled=L)
                ax.errorbar(x, y, yerr=e, marker="o", capsize=3, label=f"{L} labelled")
            _finish(ax, "alpha (weight of the self-supervised loss)")

        figure("error_vs_alpha", per_alpha, "Box: test error against alpha (paper appendix C)")
    return written


def readme(summary: dict[str, Any]) -> str:
    """A short Markdown page of a summary: scale, provenance, table of points, findings, figures."""
    exp = summary["experiment"]
    sizes = "/".join(map(str, summary["image_sizes"])) or "-"
    steps = "/".join(map(str, summary["steps"])) or "-"
    pixels = ", ".join(f"{fmt(v)} mm at {s} px" for s, v in summary.get("mm_per_px", {}).items()) or "-"
    lines = [f"# {exp}: {summary['description']}", "",
             f"{summary['runs']} runs, scale {', '.join(summary['scales']) or '-'}: {sizes} px images, "
             f"{steps} steps (paper: {PAPER_SIZE} px, {PAPER_STEPS} batches). Errors are in millimetres: "
             "the median and RMS 3D error of the triangulated points, and the per-view RMS 2D error on the "
             f"object (`rms_mm_2d`: `rms_px` x the size of one pixel at the workspace centre, {pixels}); the "
             f"paper's pixel figures at {PAPER_MM_PER_PX} mm per pixel (the paper's own figure for its "
             f"{PAPER_SIZE} px images). Mean +- std over seeds.", ""]
    for t in summary.get("two_pass", []):
        turn = t.get("coarse_rotation")
        rotation = "" if turn is None else f", rotations up to {turn:g} deg"
        lines += [f"Two passes (`s3k train --two-pass`): a coarse pass on the whole image at "
                  f"{t['coarse_size']} px ({t['coarse_steps']} steps{rotation}), a refining pass on "
                  f"{t['crop_size']} px crops "
                  "around its estimate, cut from the rendered images; pixel errors are in crop pixels.", ""]
    source = summary.get("resummarized_from")
    rev = summary.get("summary_revision")
    if source:
        lines += [f"Re-summarized by `s3k experiment {exp} --summarize-only`"
                  + (f" at revision `{rev}`" if rev else "")
                  + f" from the grid points of the summary of the runs written {source.get('generated_at')} "
                  "(the run folders are not kept here). The runs, as they recorded it:", ""]
    else:
        lines += ["Generated by `s3k experiment ... --summarize-only` from `runs/*/result.json`"
                  + (f" at revision `{rev}`." if rev else "."), ""]
    for c in summary.get("commands", []):
        lines.append(f"Command: `{c}`  ")
    if summary.get("code_revisions"):
        lines.append("Code revision (git, of the s3k package that trained the runs): "
                     + ", ".join(f"`{r}`" for r in summary["code_revisions"]) + "  ")
    if summary.get("runs_without_provenance"):
        lines.append(f"{summary['runs_without_provenance']} run(s) did not record their command and "
                     "revision.")
    if lines[-1] != "":
        lines.append("")
    keys = [k for k in ("mode", "instances", "alpha", "labelled", "labels", "unlabelled", "method")
            if any(k in p["params"] for p in summary["points"])]
    splits = ["test"] + (["train"] if any("train" in p for p in summary["points"]) else [])
    columns = (("rms_px", "rms px"), ("rms_mm_2d", "per-view mm"), ("median_mm", "median 3D mm"),
               ("rms_mm", "RMS 3D mm"))
    head = keys + ["seeds"] + [f"{s} {name}" for s in splits for _, name in columns]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in summary["points"]:
        row = [str(p["params"].get(k, "")) for k in keys] + [str(len(p["seeds"]))]
        row += [mean_std(p[s].get(m)) if s in p else "-" for s in splits for m, _ in columns]
        lines.append("| " + " | ".join(row) + " |")
    if exp == "category":
        lines += ["", f"Paper (400 px, held-out instances, {PAPER_MM_PER_PX} mm per pixel): " + ", ".join(
            f"{n}: {v} px = {fmt(paper_mm(v), 1)} mm" for n, v in PAPER_CATEGORY_TEST_PX.items()) + "."]
    lines += ["", "## Findings", "", "| paper finding | measured | reproduced? |", "|---|---|---|"]
    for f in summary["findings"]:
        lines.append(f"| {f['finding']} | {f['measured']} | {verdict(f['reproduced'])} |")
    lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in summary.get("figures", [])]
    return "\n".join(lines) + "\n"


def published(folder: Path, exp: str) -> bool:
    """True when ``folder`` holds what :func:`publish` copied there for the experiment ``exp`` (its
    ``summary.json``)."""
    try:
        doc = json.loads((folder / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("experiment") == exp and "points" in doc


def publish(exp_dir: Path, dest: Path) -> list[Path]:
    """Copy an experiment's summary.json, README.md and figures to ``dest`` (e.g. docs/results/NAME)."""
    dest.mkdir(parents=True, exist_ok=True)
    copied = []
    for path in [exp_dir / SUMMARY_FILE, exp_dir / "README.md", *sorted(exp_dir.glob("*.png"))]:
        if path.is_file():
            shutil.copyfile(path, dest / path.name)
            copied.append(dest / path.name)
    return copied
