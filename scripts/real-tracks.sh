#!/usr/bin/env bash
# Filtered tracks and one round of the way back on the real recording, for each S3K run of
# scripts/real-comparison.sh (run it first), then the summary over seeds (docs/tracks.md).
#
#   bash scripts/real-tracks.sh [RECORDING_DIR]
#
# $WORK (default /tmp/real-work, as scripts/real-comparison.sh), $SEEDS (5), $LR (the fine-tuning learning
# rate; default: each pass's own last one, as s3k train --init-from takes it: 5e-5 for the one-pass S3K
# runs), $REPEATS (fine-tunings of the loop and the control per seed, each with its own seed, default 3),
# $LABEL_CHECK / $REFERENCE_CHECK (pixels: the stand-in leaves out, the reference is triangulated without, the
# labels that far from the other cameras' agreement; default: none),
# $TRACKS (default $WORK/tracks; a --label-check variant needs its own), $OUT (default docs/results/tracks)
# and $NAME (default real): writes $OUT/$NAME-seedN.json, then $OUT/$NAME-seeds.json. Each seed's tracks,
# copies and fine-tuned runs go to $TRACKS/seedN; run it again and a finished fine-tuning is reused. The
# committed variants: LABEL_CHECK=40 TRACKS=$WORK/check40 OUT=docs/results/tracks/label-check NAME=check40;
# REFERENCE_CHECK=40 OUT=docs/results/tracks/reference-check NAME=check40; both checks, TRACKS=$WORK/check40
# OUT=docs/results/tracks/reference-check NAME=both40.
set -euo pipefail
cd "$(dirname "$0")/.."
D=$(realpath "${1:-../shared/data/real/sleap-anipose-minimal_session/minimal_session}")
WORK=${WORK:-/tmp/real-work}
SEEDS=${SEEDS:-5}
LR=${LR:-}
REPEATS=${REPEATS:-3}
OUT=${OUT:-docs/results/tracks}
TRACKS=${TRACKS:-$WORK/tracks}
NAME=${NAME:-real}
PY=${PYTHON:-python}
checks=()
if [[ -n "${LABEL_CHECK:-}" ]]; then checks+=(--label-check "$LABEL_CHECK"); fi
if [[ -n "${REFERENCE_CHECK:-}" ]]; then checks+=(--reference-check "$REFERENCE_CHECK"); fi
files=()
for ((s = 0; s < SEEDS; s++)); do
  echo "== seed $s $(date +%T)"
  "$PY" benchmarks/real_tracks.py --run "$WORK/runs/s3k-seed$s" --data "$WORK/crop" \
    --calibration "$WORK/calibration_fixed.toml" --recording "$D" --work "$TRACKS/seed$s" \
    --loop --control ${LR:+--lr "$LR"} --repeats "$REPEATS" "${checks[@]}" --out "$OUT/$NAME-seed$s.json"
  files+=("$OUT/$NAME-seed$s.json")
done
"$PY" benchmarks/real_tracks_seeds.py "${files[@]}" --out "$OUT/$NAME-seeds.json"
