#!/usr/bin/env bash
# Sets up the machine (scripts/setup.sh) and runs the main job: `s3k demo` on its built-in defaults
# (simulate the box scene, train S3K and the labels-only baseline on the same 10 labels, compare them).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export MUJOCO_GL=${MUJOCO_GL:-osmesa} PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-osmesa}
exec s3k demo "$@"
