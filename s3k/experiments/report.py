"""What a sweep reports: ``summary.json``, the figures and the ``README.md`` page of an experiment folder.

:func:`summarize` rebuilds all three from the runs' ``result.json`` files (``--summarize-only``);
:func:`publish` copies them to a results folder such as ``docs/results/NAME``.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from s3k.experiments.findings import aggregate, findings, mean_std, param_values, verdict
from s3k.experiments.grid import (
    DESCRIPTIONS,
    PAPER_CATEGORY_TEST_PX,
    PAPER_SIZE,
    PAPER_STEPS,
    RESULT_FILE,
    SUMMARY_FILE,
)
from s3k.fileio import atomic_write_json, atomic_write_text


def load_results(exp_dir: Path) -> list[dict[str, Any]]:
    """Every ``result.json`` under ``exp_dir/runs``, sorted by run name."""
    return [json.loads(path.read_text()) for path in sorted((exp_dir / "runs").glob(f"*/{RESULT_FILE}"))]


def summarize(exp_dir: Path, experiment: str | None = None) -> dict[str, Any]:
    """Write ``summary.json``, the plots and ``README.md`` of one experiment folder from its runs' JSON."""
    exp_dir = Path(exp_dir)
    experiment = experiment or exp_dir.name
    results = load_results(exp_dir)
    points = aggregate(results)
    summary: dict[str, Any] = {
        "experiment": experiment, "description": DESCRIPTIONS.get(experiment, ""),
        "runs": len(results), "scales": sorted({r.get("scale", "?") for r in results}),
        "image_sizes": sorted({r["image_size"][0] for r in results}),
        "steps": sorted({r["config"]["steps"] for r in results}),
        "paper": {"image_size": PAPER_SIZE, "steps": PAPER_STEPS},
        "error_metric": "rms_px_400: rms_px x 400 / image size (pixels at the paper's image scale)",
        "points": points, "findings": findings(experiment, points),
        "generated_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        # provenance as the runs recorded it (runs made before it was recorded count as unrecorded)
        "commands": sorted({r["command"] for r in results if r.get("command")}),
        "code_revisions": sorted({r["code_revision"] for r in results if r.get("code_revision")}),
        "runs_without_provenance": sum(1 for r in results if not r.get("command")),
    }
    if experiment == "category":
        summary["paper"]["category_test_px"] = {str(k): v for k, v in PAPER_CATEGORY_TEST_PX.items()}
    figures = plot(experiment, points, exp_dir)
    summary["figures"] = [p.name for p in figures]
    atomic_write_json(summary, exp_dir / SUMMARY_FILE)
    atomic_write_text(readme(summary), exp_dir / "README.md")
    return summary


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


_PANELS = (("rms_px_400", f"rms 2D error (px at {PAPER_SIZE} px)"), ("median_mm", "median 3D error (mm)"))


def plot(experiment: str, points: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    """Write the experiment's figures (PNG) to ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    written: list[Path] = []
    sizes = sorted({p["image_size"][0] for p in points})
    steps = sorted({p["steps"] for p in points})
    scale_note = (f"{'/'.join(map(str, sizes))} px, {'/'.join(map(str, steps))} steps "
                  f"(paper: {PAPER_SIZE} px, {PAPER_STEPS // 1000}k batches); bars: std over seeds")

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
            if metric == "rms_px_400":
                n = sorted(PAPER_CATEGORY_TEST_PX)
                ax.plot(n, [PAPER_CATEGORY_TEST_PX[k] for k in n], "k:", marker="s",
                        label="paper, held-out (400 px)")
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
    """A short Markdown page of a summary: scale, table of points, findings, figures."""
    exp = summary["experiment"]
    sizes = "/".join(map(str, summary["image_sizes"])) or "-"
    steps = "/".join(map(str, summary["steps"])) or "-"
    lines = [f"# {exp}: {summary['description']}", "",
             f"{summary['runs']} runs, scale {', '.join(summary['scales']) or '-'}: {sizes} px images, "
             f"{steps} steps (paper: {PAPER_SIZE} px, {PAPER_STEPS} batches). Errors in pixels are also "
             f"given at the paper's scale (x {PAPER_SIZE} / image size, column `px@400`). "
             "Mean +- std over seeds.", "",
             "Generated by `s3k experiment ... --summarize-only` from `runs/*/result.json`.", ""]
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
    keys = [k for k in ("mode", "instances", "alpha", "labelled", "unlabelled", "method")
            if any(k in p["params"] for p in summary["points"])]
    splits = ["test"] + (["train"] if any("train" in p for p in summary["points"]) else [])
    head = keys + ["seeds"] + [f"{s} px@400" for s in splits] + [f"{s} median mm" for s in splits]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in summary["points"]:
        row = [str(p["params"].get(k, "")) for k in keys] + [str(len(p["seeds"]))]
        row += [mean_std(p[s]["rms_px_400"]) if s in p else "-" for s in splits]
        row += [mean_std(p[s]["median_mm"]) if s in p else "-" for s in splits]
        lines.append("| " + " | ".join(row) + " |")
    if exp == "category":
        lines += ["", "Paper (400 px, held-out instances): " + ", ".join(
            f"{n}: {v}" for n, v in PAPER_CATEGORY_TEST_PX.items()) + " px."]
    lines += ["", "## Findings", "", "| paper finding | measured | reproduced? |", "|---|---|---|"]
    for f in summary["findings"]:
        lines.append(f"| {f['finding']} | {f['measured']} | {verdict(f['reproduced'])} |")
    lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in summary.get("figures", [])]
    return "\n".join(lines) + "\n"


def publish(exp_dir: Path, dest: Path) -> list[Path]:
    """Copy an experiment's summary.json, README.md and figures to ``dest`` (e.g. docs/results/NAME)."""
    dest.mkdir(parents=True, exist_ok=True)
    copied = []
    for path in [exp_dir / SUMMARY_FILE, exp_dir / "README.md", *sorted(exp_dir.glob("*.png"))]:
        if path.is_file():
            shutil.copyfile(path, dest / path.name)
            copied.append(dest / path.name)
    return copied
