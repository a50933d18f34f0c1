#!/usr/bin/env bash
# Sets up the machine (scripts/setup.sh) and runs the test suite. `--slow` also runs the slow tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export MUJOCO_GL=${MUJOCO_GL:-osmesa} PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-osmesa}
marker=(-m "not slow")
if [ "${1:-}" = "--slow" ]; then marker=(-m "slow or not slow"); shift; fi
ruff check .
mypy  # the type checker configured in pyproject.toml (package s3k)
python -m pytest -q "${marker[@]}" "$@"
