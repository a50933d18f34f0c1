#!/usr/bin/env bash
# Sets up the machine for the demo (scripts/setup.sh --demo) and runs the main job: `s3k demo` on its built-in
# defaults (render the box scene, train S3K and the labels-only baseline on the same 10 labels with the
# recommended configuration, compare them; report in s3k-demo/report/).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --demo
. .venv/bin/activate
export MUJOCO_GL=${MUJOCO_GL:-osmesa} PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-osmesa}
exec s3k demo "$@"
