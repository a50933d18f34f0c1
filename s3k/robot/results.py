"""The robot experiments' summary, ``docs/results/robot/summary.json``, from what the runs wrote.

Only measured figures go in: a field whose run was not given stays ``null``. The grasp figures come from
the JSON files of ``s3k robot grasp`` (one per detector: s3k, labels only, ground truth); the RL figures from
the ``progress.json`` of ``s3k robot train-agent`` runs (one per seed and agent): their final evaluation,
their CPU time, and the success-rate curve over seeds (mean, min, max at each evaluation step).

An agent's success rate here is the plug really in the socket: the ground-truth keypoints' distance sum
under 2.5 cm (``true_success_rate`` of the evaluations). The environment ends an episode on the agent's own
keypoints' sum, which for the keypoint agent comes from the detector (a few millimetres off per keypoint, so
a plug that is in may not count and the episode runs on); that rate is kept as ``detected_success_rate``.
The beta-VAE agent's environment reads ground-truth keypoints for its reward, so for it the two agree.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Sequence
from pathlib import Path

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json


def _read_json(path: str | Path, what: str) -> dict:
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not a {what} JSON file ({exc.msg} at line {exc.lineno})") from exc
    if not isinstance(doc, dict):
        raise UserError(f"{path}: not a {what} JSON file (not an object)")
    return doc


def grasp_rate(path: str | Path | None) -> tuple[float | None, int | None]:
    """``(success_rate, trials)`` of an ``s3k robot grasp`` result file, or ``(None, None)``."""
    if path is None:
        return None, None
    doc = _read_json(path, "grasp result")
    if "successes" not in doc or "trials" not in doc:
        raise UserError(f"{path}: not an s3k robot grasp result (no 'successes' or 'trials')")
    return doc["successes"] / doc["trials"], int(doc["trials"])


def _progress(run: str | Path) -> dict:
    doc = _read_json(Path(run) / "progress.json", "agent progress")
    if not doc.get("final"):
        raise UserError(f"{run}/progress.json: the run has no final evaluation yet",
                        hint="finish it with s3k robot train-agent --resume")
    return doc


def _true(evaluation: dict) -> float:
    """The share of episodes with the plug really in (older runs without it: the detected rate)."""
    return float(evaluation.get("true_success_rate", evaluation["success_rate"]))


def rl_final(runs: Sequence[str | Path]) -> dict | None:
    """``{"mean", "min", "max", "per_seed", "env_steps", "cpu_hours"}`` of the final success rates of agent
    runs (one per seed), or None."""
    if not runs:
        return None
    per_seed, steps, cpu = [], set(), []
    for run in runs:
        final = _progress(run)["final"]
        per_seed.append({"seed": final["seed"], "success_rate": _true(final),
                         "detected_success_rate": final["success_rate"]})
        steps.add(int(final["env_steps"]))
        cpu.append(final.get("cpu_seconds"))
    rates = [p["success_rate"] for p in per_seed]
    cpu_hours = None if None in cpu else round(sum(cpu) / 3600, 3)
    return {"mean": statistics.fmean(rates), "min": min(rates), "max": max(rates), "per_seed": per_seed,
            "env_steps": sorted(steps), "cpu_hours": cpu_hours}


def rl_curve(runs: Sequence[str | Path]) -> dict | None:
    """The success-rate curve over seeds: ``{"env_steps": [...], "mean": [...], "min": [...], "max": [...],
    "seeds": n}`` at the evaluation steps every run has, or None."""
    if not runs:
        return None
    curves = []
    for run in runs:
        curves.append({int(e["env_steps"]): _true(e) for e in _progress(run)["evaluations"]})
    steps = sorted(set.intersection(*(set(c) for c in curves)))
    return {"env_steps": steps,
            "mean": [statistics.fmean(c[s] for c in curves) for s in steps],
            "min": [min(c[s] for c in curves) for s in steps],
            "max": [max(c[s] for c in curves) for s in steps],
            "seeds": len(curves)}


def write_summary(out: str | Path, *, grasp_s3k=None, grasp_labels_only=None, grasp_ground_truth=None,
                  rl_keypoints: Sequence = (), rl_beta_vae: Sequence = (),
                  machine: str | None = None) -> dict:
    """Writes the summary (atomically) and returns it."""
    rates = {name: grasp_rate(p) for name, p in (("s3k", grasp_s3k), ("labels_only", grasp_labels_only),
                                                  ("ground_truth", grasp_ground_truth))}
    trials = sorted({t for _, t in rates.values() if t is not None})
    kp, vae = rl_final(rl_keypoints), rl_final(rl_beta_vae)
    env_steps = sorted({s for r in (kp, vae) if r is not None for s in r.pop("env_steps")})
    curves = {"keypoints": rl_curve(rl_keypoints), "beta_vae": rl_curve(rl_beta_vae)}
    summary = {
        "grasp_success": {name: rate for name, (rate, _) in rates.items()} | {
            "trials": trials[0] if len(trials) == 1 else (trials or None)},
        "rl_final_success": {"keypoints": kp, "beta_vae": vae,
                             "env_steps": env_steps[0] if len(env_steps) == 1 else (env_steps or None)},
        "rl_success_curve": curves,
        "machine": machine,
    }
    atomic_write_json(summary, out)
    return summary


GRASP_SOURCES = ("s3k", "labels_only", "ground_truth")


def _spread(values: Sequence[float]) -> dict:
    return {"mean": statistics.fmean(values), "sd": statistics.pstdev(values), "min": min(values),
            "max": max(values), "per_seed": [float(v) for v in values]}


def grasps_over_seeds(results: dict[tuple[str, int], dict], seeds: Sequence[int]) -> dict:
    """The grasp results of ``s3k robot grasp`` per source (``GRASP_SOURCES``) and detector seed, combined:
    per source the success rate over the seeds, the rate per arrangement (mean over seeds), the median aim
    error over every trial and the trials in all."""
    out: dict = {}
    for src in GRASP_SOURCES:
        docs = [results[src, s] for s in seeds]
        arrangements = docs[0]["per_arrangement"]
        aims = [t["aim_error_mm"] for d in docs for t in d["per_trial"]]
        finite = [a for a in aims if a == a]  # NaN: no keypoints, no aim
        out[src] = {
            "success_rate": _spread([d["success_rate"] for d in docs]),
            "per_arrangement": {a: statistics.fmean(d["per_arrangement"][a] for d in docs)
                                for a in arrangements},
            "aim_error_mm_median": statistics.median(finite) if finite else None,
            "trials": sum(int(d["trials"]) for d in docs),
        }
    return out


def with_grasp(summary: dict, record: dict, trials: int, tests: dict[str, list[dict] | None]) -> dict:
    """``summary`` (the robot summary, agents' figures kept) with ``grasp_success`` from ``record``
    (:func:`grasps_over_seeds` plus ``scale``, ``seeds``, ``arrangements``, ``git_revision``), its ``scale``
    saying what the grasp ran with, and the plush detectors' test figures replaced by ``tests`` (per model,
    the evaluations of its seeds' detectors; None: not known, so none are given)."""
    summary = dict(summary)
    summary["grasp_success"] = {
        **{src: record[src]["success_rate"]["mean"] for src in GRASP_SOURCES},
        "trials": trials, "trials_in_all": record["s3k"]["trials"],
        "arrangements": len(record["arrangements"]), "detector_seeds": len(record["seeds"]),
        "per_seed": {src: record[src]["success_rate"]["per_seed"] for src in GRASP_SOURCES},
        "detectors": "two-pass, from benchmarks/accuracy.py --scene plush",
        "record": "grasp.json",
        "git_revision": record["git_revision"],
    }
    # the robot benchmark's scale and detector figures describe its own grasp detectors: now these ones
    # (its agents' part is in ``agents_scale``; a summary from before that field has it at the scale's end)
    old = str(summary.get("scale", ""))
    agents = summary.get("agents_scale") or (old[old.index("insertion views"):] if "insertion views" in old
                                             else old)
    summary["scale"] = f"grasp: {record['scale']}" + (f"; agents: {agents}" if agents else "")
    figures = dict(summary.get("detectors_test") or {})
    for src in ("s3k", "labels_only"):
        evaluations = tests.get(src)
        if evaluations:
            figures[src] = {k: _spread([e[k] for e in evaluations])
                            for k in ("median_mm", "rms_mm", "pck_10mm")}
        else:
            figures.pop(src, None)
    summary["detectors_test"] = figures
    return summary
