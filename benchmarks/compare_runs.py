"""Two run folders trained alike (e.g. by two revisions of s3k): for every model and checkpoint file they both
hold, whether the weights are identical and their largest absolute difference, and whether the two-pass
files (estimates, crop rule) are byte for byte the same. Prints one JSON object.

Example (``tests/data/old_runs/make_old_runs.py`` run under each revision)::

    python benchmarks/compare_runs.py /tmp/old /tmp/new
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import shlex
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.common import git_revision, machine_info  # noqa: E402
from s3k.detector import load_torch_file  # noqa: E402
from s3k.run_folder import RunFolder  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("before", type=Path)
    p.add_argument("after", type=Path)
    args = p.parse_args(argv)
    out: dict = {"command": shlex.join(["python", "benchmarks/compare_runs.py",
                                        *(sys.argv[1:] if argv is None else argv)]),
                 "git_revision": git_revision(), "machine": machine_info(), "weights": {}, "files": {}}
    for path in sorted(args.before.rglob("*.pt")):
        rel = path.relative_to(args.before)
        other = args.after / rel
        if not other.is_file():
            continue
        a = load_torch_file(path, "model", ("model",))["model"]
        b = load_torch_file(other, "model", ("model",))["model"]
        diff = max(float((a[k].double() - b[k].double()).abs().max()) if a[k].numel() else 0.0 for k in a)
        out["weights"][rel.as_posix()] = {"identical": a.keys() == b.keys() and diff == 0.0, "max_abs": diff}
    for path in sorted(args.before.rglob("*")):
        if path.name in (RunFolder.ESTIMATES, RunFolder.TWO_PASS) and (args.after / path.relative_to(
                args.before)).is_file():
            rel = path.relative_to(args.before)
            out["files"][rel.as_posix()] = filecmp.cmp(path, args.after / rel, shallow=False)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
