#!/usr/bin/env bash
# Reruns, on this checkout, the commands that a careless or hostile user tried on the newer commands
# (calibrate, check-calibration --recalibrate, track's filters, add-frames, label --public-url, train --resume)
# and prints one line per case: what it did, and whether that is a one-line refusal or correct behaviour.
# Each file scripts/loose-ends/*.sh defines its cases with `refuse` and `accept` (scripts/loose-ends/lib.sh).
# Usage: bash scripts/loose-ends.sh [AREA ...]   (after `bash scripts/setup.sh`; exits 1 if any case fails)
set -uo pipefail
cd "$(dirname "$0")/.."
[ -f .venv/bin/activate ] && . .venv/bin/activate
export MUJOCO_GL=${MUJOCO_GL:-osmesa} PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-osmesa}
. scripts/loose-ends/lib.sh
areas=("$@")
[ ${#areas[@]} -gt 0 ] || areas=($(cd scripts/loose-ends && ls *.sh | grep -v '^lib\.sh$' | sed 's/\.sh$//'))
for area in "${areas[@]}"; do
    echo "== $area"
    . "scripts/loose-ends/$area.sh"
done
summary
