"""Several sessions against one over several draws of the sessions themselves: ``benchmarks/sessions.py`` run
once per draw (other ``--session-seeds`` and ``--new-rig-seeds``: other camera placements, poses and
lighting), each in its own ``--work``, pooled here.

Within one run of ``sessions.py`` the training seeds change, the sessions do not: B's labels always lie on the
same placement of the training rig, so a placement that happens to suit training favours B in every seed.
Pooled over draws, per held-out session (``s4``: a new placement of the training rig; a new-rig session by its
rig, e.g. ``rig low``): each draw's A - B (its training seeds' mean of the paired difference on the same
points, with the draw's 95% bootstrap interval over frames when it has one seed), the mean over draws with a
95% t-interval, and in how many draws A is lower, with the sign test's two-sided p (exact binomial, one half
per draw under no difference; a draw's difference can dwarf the others', which widens the t-interval but not
the count), and in how many draws each model's lead is clear of zero over that draw's frames; both models'
medians per draw.

    python benchmarks/sessions_draws.py D1/summary.json D2/summary.json D3/summary.json [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info, t_interval, write_and_emit  # noqa: E402

HELD_OUT = "s4"


def held_out_roles(summary: dict[str, Any]) -> dict[str, str]:
    """``{session: role}``: s4 as ``training rig (s4)``, each new-rig session as ``rig NAME``."""
    roles = {HELD_OUT: f"training rig ({HELD_OUT})"}
    for session, about in summary["setup"].get("new_rigs", {}).items():
        roles[session] = f"rig {about['rig']}"
    return roles


def draw_figures(path: Path) -> dict[str, Any]:
    """One draw's per-role A - B (mean over its seeds) and medians, from its ``sessions.py`` summary."""
    try:
        summary = json.loads(path.read_text())
        per_seed = summary["paired"]["per_seed"]
        setup = summary["setup"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"{path}: not a summary of benchmarks/sessions.py ({type(e).__name__}: {e})"
                         ) from None
    if not per_seed:
        raise SystemExit(f"{path}: no training seed has both A and B evaluated yet; finish its runs first")
    out: dict[str, Any] = {"summary": str(path), "session_seeds": setup.get("session_seeds"),
                           "new_rigs": setup.get("new_rigs"), "revision": summary.get("git_revision"),
                           "training_seeds": sorted(int(s) for s in per_seed), "held_out": {}}
    for session, role in held_out_roles(summary).items():
        seeds = [p[session] for p in per_seed.values() if session in p]
        if not seeds:
            continue
        out["held_out"][role] = {
            "session": session,
            "mean_diff_mm": float(np.mean([s["mean_diff_mm"] for s in seeds])),
            "ci95_mm_over_frames": seeds[0]["ci95_mm"] if len(seeds) == 1 else None,
            "median_mm_A": float(np.mean([s["median_mm"][0] for s in seeds])),
            "median_mm_B": float(np.mean([s["median_mm"][1] for s in seeds])),
        }
    return out


def sign_test_p(lower: int, draws: int) -> float:
    """Two-sided exact sign test: the chance of a count at least as far from ``draws / 2`` as ``lower`` when
    either model is as likely to win each draw."""
    far = abs(lower - draws / 2)
    return float(min(1.0, sum(math.comb(draws, k) for k in range(draws + 1) if abs(k - draws / 2) >= far)
                     / 2 ** draws))


def pool(draws: list[dict[str, Any]]) -> dict[str, Any]:
    """Per role held out in every draw: the draws' A - B, their mean with a t-interval, the count A wins."""
    roles = [r for r in draws[0]["held_out"] if all(r in d["held_out"] for d in draws)]
    out = {}
    for role in roles:
        diffs = [d["held_out"][role]["mean_diff_mm"] for d in draws]
        lower = int(sum(x < 0 for x in diffs))
        # a draw of several training seeds has no interval over frames: clear for neither model
        intervals = [d["held_out"][role]["ci95_mm_over_frames"] or [0.0, 0.0] for d in draws]
        out[role] = {
            "per_draw_mm": diffs,
            "mean_diff_mm": float(np.mean(diffs)),
            "ci95_mm_over_draws": t_interval(diffs),
            "draws_A_lower": lower,
            "draws": len(diffs),
            "sign_test_p": sign_test_p(lower, len(diffs)),
            "draws_A_lower_clear_of_zero": sum(high < 0 for _, high in intervals),
            "draws_B_lower_clear_of_zero": sum(low > 0 for low, _ in intervals),
            "median_mm_A": float(np.mean([d["held_out"][role]["median_mm_A"] for d in draws])),
            "median_mm_B": float(np.mean([d["held_out"][role]["median_mm_B"] for d in draws])),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("summaries", nargs="+", help="summary.json of benchmarks/sessions.py, one per draw")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)
    draws = [draw_figures(Path(s)) for s in a.summaries]
    seeds = [tuple(sorted((d["session_seeds"] or {}).values())) for d in draws]
    if len(set(seeds)) < len(seeds):
        p.error("two summaries drew the same sessions (--session-seeds): give one summary per draw")
    pooled = pool(draws)
    for role, f in pooled.items():
        ci = f["ci95_mm_over_draws"]
        print(f"{role}: A - B {f['mean_diff_mm']:+.2f} mm over {f['draws']} draws"
              + (f" [{ci[0]:+.2f}, {ci[1]:+.2f}]" if ci else "")
              + f"; per draw {', '.join(f'{x:+.2f}' for x in f['per_draw_mm'])}; A lower in "
              f"{f['draws_A_lower']} of {f['draws']} (sign test p {f['sign_test_p']:.3f}); clear of zero "
              f"over the draw's frames: A in {f['draws_A_lower_clear_of_zero']}, B in "
              f"{f['draws_B_lower_clear_of_zero']}; median A {f['median_mm_A']:.2f}, "
              f"B {f['median_mm_B']:.2f}",
              file=sys.stderr)
    result = {
        "command": shlex.join(["python", "benchmarks/sessions_draws.py",
                               *(sys.argv[1:] if argv is None else argv)]),
        "revision": git_revision(), "machine": machine_info(),
        "what": "A's minus B's 3D error (mm) on the same test points of each held-out session, per draw of "
                "the sessions (the mean over its training seeds), pooled over draws with a 95% t-interval "
                "and a two-sided sign test on the draws A wins",
        "pooled": pooled, "draws": draws,
    }
    write_and_emit(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
