"""The label curve (``benchmarks/label_curve.py``): the box headline at several counts of labelled frames, S3K
and labels only, over seeds, and how many labels labels only needs to match S3K at 10.

It is the accuracy benchmark's way (:mod:`s3k.experiments.accuracy`): each seed's scene rendered once with a
pool of labelled frames, the labelled frames of every count chosen from that pool by the labelling app's
*poses in proportion* ranking (the picks of a larger count contain those of a smaller one), each model
trained with ``s3k train --preset PRESET`` in its own process (CPU time recorded), evaluated on the seed's
test frames. Every (labels, model, seed) is a job of its own, kept in the working folder::

    WORK/box384-L100-seed0/                          the seed's rendered pool (as the accuracy benchmark's)
    WORK/box384-L100-representative-n5-seed0/        the view with 5 labelled frames (images linked)
    WORK/L5/s3k-seed0/                               the run; -cpu.json its CPU time, -test.json its test
    WORK/L5/s3k-seed0-result.json                    the job's result

A job with a result is skipped; a run begun and killed is resumed (``s3k train --resume``), its CPU minutes
so far kept. The summary (``summary.json``) and the figure (``label-curve.png``) are made from the jobs'
result files only, so they can be written again from a working folder at any time.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import logging
import statistics
import textwrap
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.base.messages import NOTE
from s3k.experiments.accuracy import (
    MODELS,
    data_names,
    evaluate,
    finished,
    labelled_view,
    read_record,
    render_pool,
    run_jobs,
    timed,
    train_command,
)
from s3k.run_folder import RunFolder
from s3k.train.presets import PRESETS

log = logging.getLogger(__name__)

#: The label counts of the curve.
LABEL_COUNTS = (5, 10, 20, 50, 100)
#: The figures kept per job (from the test evaluation).
JOB_FIGURES = ("median_mm", "rms_mm", "pck_5mm", "pck_10mm", "rms_px")
#: The figures of the summary and the curve.
CURVE_FIGURES = ("median_mm", "rms_mm", "pck_10mm")
#: The label count whose S3K figures labels only is measured against (``CurveOptions.reference``).
REFERENCE_LABELS = 10
SUMMARY = "summary.json"
FIGURE = "label-curve.png"
MODEL_NAMES = {"s3k": "S3K", "labels_only": "labels only"}
#: The summary's key of the curves of other configurations drawn beside this one (:func:`add_curve`).
ADDED = "added_curves"


@dataclasses.dataclass
class CurveOptions:
    """What the curve trains: the accuracy benchmark's options (attribute names as its ``args``) and the
    label counts. :meth:`from_preset` fills the two-pass sizes and steps from a preset."""

    labels: tuple[int, ...] = LABEL_COUNTS
    seeds: int = 3
    scene: str = "box"
    render: int = 384
    unlabelled: int = 2000
    test: int = 200
    label_pool: int = 100
    label_choice: str = "representative"
    unlabelled_arrangements: int = 0
    passes: int = 2
    coarse_size: int = 96
    crop_size: int = 192
    steps: int = 4000
    coarse_steps: int | None = None
    train_options: str = ""
    parallel: int = 2
    backend: str = "local"
    address: str | None = None
    reference: int = REFERENCE_LABELS
    preset: str | None = None

    def __post_init__(self) -> None:
        self.labels = tuple(sorted(set(int(n) for n in self.labels)))
        if not self.labels or self.labels[0] < 1:
            raise ValueError(f"labels: counts must be >= 1, got {self.labels}")
        if self.labels[-1] > self.label_pool:
            raise ValueError(f"labels: {self.labels[-1]} labelled frames from a pool of {self.label_pool} "
                             "(raise --label-pool)")

    @classmethod
    def from_preset(cls, preset: str | None, **given: Any) -> CurveOptions:
        """The options with ``s3k train --preset PRESET``'s two-pass sizes and steps, unless ``given`` (None:
        no preset, the ``given`` options and the defaults above). The trainings' configuration is the preset's
        (:func:`s3k.experiments.accuracy.train_config`), their commands built from it."""
        if preset is None:
            return cls(**{k: v for k, v in given.items() if v is not None})
        cfg = PRESETS[preset].config
        defaults: dict[str, Any] = {"preset": preset, "passes": 2 if cfg.passes.two_pass else 1,
                                    "steps": cfg.schedule.steps}
        if cfg.passes.two_pass:
            defaults.update(coarse_size=cfg.passes.coarse_size, coarse_steps=cfg.passes.coarse_steps,
                            crop_size=cfg.passes.crop_size)
        defaults.update({k: v for k, v in given.items() if v is not None})
        return cls(**defaults)


@dataclasses.dataclass(frozen=True)
class Job:
    """One (labels, model, seed) of the curve."""

    labels: int
    model: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.model} {self.labels} labels seed {self.seed}"

    def run(self, work: Path) -> Path:
        return work / f"L{self.labels}" / f"{self.model}-seed{self.seed}"

    def record(self, work: Path) -> Path:
        """The run's CPU record (:func:`s3k.experiments.accuracy.run_jobs`)."""
        run = self.run(work)
        return run.with_name(run.name + "-cpu.json")

    def result(self, work: Path) -> Path:
        run = self.run(work)
        return run.with_name(run.name + "-result.json")

    def revisions(self, work: Path) -> Path:
        """The revisions the run's training was started or resumed at, in order."""
        run = self.run(work)
        return run.with_name(run.name + "-revisions.json")

    def trained_at(self, work: Path) -> list[str]:
        path = self.revisions(work)
        return list(json.loads(path.read_text())) if path.is_file() else []


def jobs(opts: CurveOptions) -> list[Job]:
    """Every job of the curve, seed by seed (a whole curve of seed 0 first), S3K before labels only."""
    return [Job(n, m, s) for s in range(opts.seeds) for n in opts.labels for m in MODELS]


def view_name(opts: CurveOptions, labels: int, seed: int) -> str:
    """The folder of the seed's view with ``labels`` labelled frames."""
    pool = data_names(opts, seed)[0].removesuffix(f"-seed{seed}")
    return f"{pool}-{opts.label_choice}-n{labels}-seed{seed}"


def prepare_data(opts: CurveOptions, work: Path, seeds: Iterable[int] | None = None
                 ) -> dict[tuple[int, int], Path]:
    """Each seed's pool (of ``seeds``, default all) rendered once and its view for every label count:
    ``{(labels, seed): dataset}``."""
    data = {}
    for s in range(opts.seeds) if seeds is None else seeds:
        pool = None
        for n in opts.labels:
            out = work / view_name(opts, n, s)
            if not (out / "s3k.json").is_file():
                pool = pool or render_pool(opts, s, work)
                with timed(work, f"label_choice-n{n}-seed{s}"):
                    labelled_view(pool, out, opts.label_choice, s, labelled=n)
            data[n, s] = out
    return data


def pending_trainings(opts: CurveOptions, work: Path, data: dict[tuple[int, int], Path],
                      revision: str = "unknown") -> list[tuple[str, list[str], Path]]:
    """The training commands of the jobs without a result whose run has not finished (a run begun is
    resumed: its command has ``--resume``), in :func:`jobs` order; ``revision`` is added to each one's
    revisions."""
    out = []
    for job in jobs(opts):
        run = job.run(work)
        if (job.labels, job.seed) not in data or job.result(work).is_file() or finished(run, opts.passes):
            continue
        run.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json([*job.trained_at(work), revision], job.revisions(work))
        out.append((job.name, train_command(opts, data[job.labels, job.seed], run, job.seed, job.model),
                    job.record(work)))
    return out


def write_results(opts: CurveOptions, work: Path, data: dict[tuple[int, int], Path],
                  revision: str) -> list[Job]:
    """Evaluate every finished run without a result and write its result; returns the jobs written."""
    written = []
    for job in jobs(opts):
        run, path = job.run(work), job.result(work)
        if (job.labels, job.seed) not in data or path.is_file() or not finished(run, opts.passes):
            continue
        metrics = evaluate(run, data[job.labels, job.seed])
        spent = read_record(job.record(work))
        result = {"labels": job.labels, "model": job.model, "seed": job.seed, "run": str(run),
                  "data": str(data[job.labels, job.seed]),
                  **{k: float(metrics[k]) for k in JOB_FIGURES if k in metrics},
                  "train_cpu_minutes": spent["cpu_minutes"], "train_wall_minutes": spent["wall_minutes"],
                  "trained_at_revisions": job.trained_at(work), "evaluated_at_revision": revision}
        atomic_write_json(result, path)
        written.append(job)
    return written


def read_results(opts: CurveOptions, work: Path) -> tuple[dict[Job, dict], list[Job]]:
    """The result of every job that has one, and the jobs that have none."""
    found, missing = {}, []
    for job in jobs(opts):
        path = job.result(work)
        if path.is_file():
            found[job] = json.loads(path.read_text())
        else:
            missing.append(job)
    return found, missing


def unfinished(opts: CurveOptions, work: Path, missing: list[Job]) -> list[dict[str, Any]]:
    """The jobs without a result whose training has begun: the steps each pass has done (``[step, steps]``
    from its ``progress.json``) and the CPU and wall minutes spent so far, killed attempts included."""
    out = []
    for job in missing:
        run = RunFolder(job.run(work))
        if not run.path.is_dir():
            continue
        parts = {"coarse": run.coarse, "fine": run.fine} if opts.passes == 2 else {"one": run}
        steps = {}
        for name, part in parts.items():
            if part.progress.is_file():
                doc = json.loads(part.progress.read_text())
                steps[name] = [int(doc["step"]), int(doc["steps"])]
        spent = read_record(job.record(work))
        out.append({"job": job.name, "steps": steps, "cpu_minutes": spent["cpu_minutes"],
                    "wall_minutes": spent["wall_minutes"]})
    return out


def _stats(values: list[float]) -> dict[str, Any]:
    return {"mean": statistics.fmean(values), "sd": statistics.stdev(values) if len(values) > 1 else 0.0,
            "min": min(values), "max": max(values), "per_seed": values}


def curve_summary(opts: CurveOptions, results: dict[Job, dict]) -> dict[str, Any]:
    """Per model and label count, each figure's mean, spread and per-seed values (seeds in order, those with
    a result), and per figure the smallest label count at which labels only's mean is as good as S3K's at
    ``opts.reference`` labels (None where no count measured reaches it)."""
    curve: dict[str, Any] = {}
    for m in MODELS:
        curve[m] = {}
        for n in opts.labels:
            done = sorted((job.seed, r) for job, r in results.items() if job.model == m and job.labels == n)
            if not done:
                continue
            entry: dict[str, Any] = {"seeds": [s for s, _ in done]}
            for k in (*CURVE_FIGURES, "train_cpu_minutes"):
                entry[k] = _stats([float(r[k]) for _, r in done])
            curve[m][str(n)] = entry
    match: dict[str, Any] = {}
    reference = curve["s3k"].get(str(opts.reference))
    for k in CURVE_FIGURES:
        if reference is None:
            match[k] = None
            continue
        target = reference[k]["mean"]
        reached = [int(n) for n, e in curve["labels_only"].items()
                   if (e[k]["mean"] >= target if k.startswith("pck") else e[k]["mean"] <= target)]
        match[k] = {"s3k_at_reference": target, "labels_only_labels": min(reached) if reached else None,
                    "labels_measured": [int(n) for n in curve["labels_only"]]}
    return {"curve": curve, "reference_labels": opts.reference, "labels_only_to_match_s3k": match}


def answer(summary: dict[str, Any]) -> str:
    """The sentence a reader takes away: how many labels labels only needs to match S3K at the reference
    count (10)."""
    parts = []
    at = summary["reference_labels"]
    for k, unit in (("median_mm", "mm median"), ("rms_mm", "mm RMS")):
        got = summary["labels_only_to_match_s3k"].get(k)
        if got is None:
            parts.append(f"{k}: no S3K result at {at} labels")
            continue
        measured = max(got["labels_measured"], default=0)
        need = (f"{got['labels_only_labels']} labels" if got["labels_only_labels"] is not None
                else f"more than {measured} labels (not reached at any count measured)")
        parts.append(f"S3K at {at} labels: {got['s3k_at_reference']:.3g} {unit}; labels only "
                     f"reaches it with {need}")
    return "; ".join(parts)


def write_summary(opts: CurveOptions, work: Path, results_dir: Path, command: str, revision: str,
                  machine: dict[str, Any], notes: str | None = None) -> dict[str, Any]:
    """``results_dir/summary.json`` and ``results_dir/label-curve.png`` from the jobs' result files."""
    results, missing = read_results(opts, work)
    summary: dict[str, Any] = {
        "command": command, "git_revision": revision, "machine": machine,
        "avx512_bf16": "avx512_bf16" in machine.get("cpu_flags", []),
        "scale": (f"{opts.scene} rendered at {opts.render} px, a pool of {opts.label_pool} labelled frames "
                  f"of which {', '.join(map(str, opts.labels))} are trained on ({opts.label_choice} choice, "
                  f"nested) + {opts.unlabelled} unlabelled + {opts.test} test frames; "
                  + (f"two passes: coarse {opts.coarse_size} px, {opts.coarse_steps or opts.steps} steps; "
                     f"crops {opts.crop_size} px, {opts.steps} steps" if opts.passes == 2
                     else f"one pass at {opts.coarse_size} px, {opts.steps} steps")
                  + (f"; train options {opts.train_options!r}" if opts.train_options else "")),
        "train_options": opts.train_options,
        "labels": list(opts.labels), "seeds": list(range(opts.seeds)),
        "jobs_with_results": len(results),
        "missing_jobs": [job.name for job in missing],
        "unfinished_jobs": unfinished(opts, work, missing),
        "trained_at_revisions": sorted({v for r in results.values()
                                        for v in r.get("trained_at_revisions", [])}),
        "evaluated_at_revisions": sorted({r.get("evaluated_at_revision", "unknown")
                                          for r in results.values()}),
        **curve_summary(opts, results),
    }
    summary["answer"] = answer(summary)
    if notes:
        summary["notes"] = notes
    if (results_dir / SUMMARY).is_file():  # curves added beside this one (add_curve) stay
        added = json.loads((results_dir / SUMMARY).read_text()).get(ADDED)
        if added:
            summary[ADDED] = added
    results_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(summary, results_dir / SUMMARY)
    plot_curve(summary, results_dir / FIGURE)
    return summary


def add_curve(results_dir: Path, name: str, others: list[Path], command: str) -> dict[str, Any]:
    """Put the curve of another configuration (``others``: the summaries of the same benchmark with, e.g.,
    another encoder, each at some of the counts, joined into one curve) beside this one's, in
    ``results_dir``'s summary under ``added_curves`` (named ``name``, with where each count came from: its
    summary's command, revision, scale and seeds), and draw it in the same figure. An added curve of that
    name is replaced; a later summary of this curve keeps it.

    Raises:
        UserError: ``results_dir`` holds no summary, one of ``others`` is no label-curve summary, or two of
            them hold the same model at the same count.
    """
    path = results_dir / SUMMARY
    if not path.is_file():
        raise UserError(f"{path}: no label-curve summary to add a curve to",
                        hint="give --results the folder of a label curve's summary.json")
    curve: dict[str, dict[str, Any]] = {}
    sources: list[dict[str, Any]] = []
    where: dict[tuple[str, str], Path] = {}
    for other in others:
        try:
            theirs = json.loads(Path(other).read_text())
            items = [(m, str(n), e) for m, per_count in theirs["curve"].items() for n, e in per_count.items()]
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
            raise UserError(f"{other}: not a label-curve summary ({type(e).__name__}: {e})",
                            hint="give the summary.json that benchmarks/label_curve.py wrote") from None
        for m, n, point in items:
            if (m, n) in where:
                raise UserError(f"{other}: {MODEL_NAMES.get(m, m)} at {n} labels is in {where[m, n]} too",
                                hint="give each label count's summary once")
            where[m, n] = other
            curve.setdefault(m, {})[n] = point
        sources.append({"from": str(other), "counts": sorted({int(n) for _, n, _ in items}),
                        **{k: theirs.get(k) for k in ("command", "git_revision", "scale", "seeds",
                                                      "trained_at_revisions")},
                        "train_options": train_options_of(theirs)})
    for m in curve:
        curve[m] = dict(sorted(curve[m].items(), key=lambda kv: int(kv[0])))
    summary = json.loads(path.read_text())
    summary.setdefault(ADDED, {})[name] = {"added_by": command, "sources": sources, "curve": curve}
    atomic_write_json(summary, path)
    plot_curve(summary, results_dir / FIGURE)
    return summary


def train_options_of(summary: dict[str, Any]) -> str:
    """The training options a curve's summary (or an added curve's source) was trained with: its
    ``train_options`` field, or for a summary written before that field, what its ``scale`` names after
    "; train options "; "" where neither names any."""
    given = summary.get("train_options")
    if isinstance(given, str):
        return given
    _, marker, named = str(summary.get("scale", "")).partition("; train options ")
    if not marker:
        return ""
    try:
        value = ast.literal_eval(named)
    except (ValueError, SyntaxError):
        return named
    return value if isinstance(value, str) else named


def plotted_counts(summary: dict[str, Any]) -> list[int]:
    """The label counts the figure marks: its own and those of every curve added beside it."""
    curves = [summary["curve"], *(c["curve"] for c in summary.get(ADDED, {}).values())]
    return sorted({int(n) for curve in curves for per_count in curve.values() for n in per_count}
                  | {int(n) for n in summary["labels"]})


def plot_curve(summary: dict[str, Any], path: Path) -> Path:
    """Median and RMS against labelled frames, one line per model (the mean over seeds), the seeds' range as
    error bars, S3K's figure at the reference count as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, NullLocator, ScalarFormatter

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    colours = {"s3k": "tab:blue", "labels_only": "tab:orange"}
    curves = [(summary["curve"], "", "o", "-")]
    curves += [(c["curve"], f", {name}", "s", ":") for name, c in summary.get(ADDED, {}).items()]
    counts = plotted_counts(summary)  # both axes mark the same counts
    for ax, (k, label) in zip(axes, (("median_mm", "median 3D error (mm)"), ("rms_mm", "RMS 3D error (mm)"))):
        for curve, suffix, marker, ls in curves:
            for m, per_count in curve.items():
                if not per_count:
                    continue
                xs = [int(n) for n in per_count]
                mean = [e[k]["mean"] for e in per_count.values()]
                low = [e[k]["mean"] - e[k]["min"] for e in per_count.values()]
                high = [e[k]["max"] - e[k]["mean"] for e in per_count.values()]
                ax.errorbar(xs, mean, yerr=[low, high], marker=marker, ls=ls, capsize=3, color=colours.get(m),
                            label=MODEL_NAMES.get(m, m) + suffix)
        at = summary["reference_labels"]
        reference = summary["curve"].get("s3k", {}).get(str(at))
        if reference is not None:
            ax.axhline(reference[k]["mean"], color=colours["s3k"], ls="--", lw=0.8,
                       label=f"S3K at {at} labels")
        ax.set_xscale("log")
        if k == "rms_mm":  # labels only's RMS can be ten times S3K's
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(ScalarFormatter())
            ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(counts, [str(n) for n in counts])
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set_xlabel("labelled frames")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # no line before the first result
            ax.legend(fontsize=8)
    seeds = len(summary["seeds"])
    caption = f"{summary['scale']}; means over {seeds} seed{'s' if seeds > 1 else ''}, bars: the seeds' range"
    for name, c in summary.get(ADDED, {}).items():
        sources = c.get("sources", [c])  # one per summary joined (an older summary's entry is its own)
        options = sorted({repr(o) if o else "none" for o in map(train_options_of, sources)})
        seeds_at = ", ".join(f"seeds {x.get('seeds')} at {'/'.join(map(str, x.get('counts', [])))} labels"
                             for x in sources)
        caption += f"; dotted, {name}: train options {' / '.join(options)}, {seeds_at}"
    fig.suptitle(textwrap.fill(caption, 160), fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_curve(opts: CurveOptions, work: Path, results_dir: Path, command: str, revision: str,
              machine: dict[str, Any], summary_only: bool = False,
              notes: str | None = None) -> dict[str, Any]:
    """Render every seed, train the jobs without a result (``opts.parallel`` at a time, in :func:`jobs`
    order: seed 0's first, and a seed's next job starts as soon as a slot is free, so no core waits for a
    seed's longest training), evaluate them, and write the summary and figure; with ``summary_only`` only
    the last step, from the results there are and those of runs that have finished since (evaluated,
    nothing trained)."""
    work.mkdir(parents=True, exist_ok=True)
    if summary_only:  # runs finished while others train on: evaluated now, nothing rendered or trained
        views = {(n, s): work / view_name(opts, n, s) for s in range(opts.seeds) for n in opts.labels}
        write_results(opts, work, {k: v for k, v in views.items() if (v / "s3k.json").is_file()}, revision)
    else:
        data = prepare_data(opts, work)
        run_jobs(pending_trainings(opts, work, data, revision), opts.parallel, backend=opts.backend,
                 address=opts.address)
        for job in write_results(opts, work, data, revision):
            log.log(NOTE, f"result {job.name}")
    return write_summary(opts, work, results_dir, command, revision, machine, notes)
