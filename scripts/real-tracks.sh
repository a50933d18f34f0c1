#!/usr/bin/env bash
# Filtered tracks and one round of the way back on the real recording, for each S3K run of
# scripts/real-comparison.sh (run it first), then the summary over seeds (docs/tracks.md).
#
#   bash scripts/real-tracks.sh [RECORDING_DIR]
#
# $WORK (default /tmp/real-work, as scripts/real-comparison.sh), $SEEDS (5), $LR (the fine-tuning learning
# rate, default 5e-5: the S3K runs' own last one), $REPEATS (fine-tunings of the loop and the control per seed,
# each with its own seed, default 3), $OUT (default docs/results/tracks): writes
# $OUT/real-seedN.json, then $OUT/real-seeds.json. Each seed's tracks, copies and fine-tuned runs go to
# $WORK/tracks/seedN; run it again and a finished fine-tuning is reused.
set -euo pipefail
cd "$(dirname "$0")/.."
D=$(realpath "${1:-../shared/data/real/sleap-anipose-minimal_session/minimal_session}")
WORK=${WORK:-/tmp/real-work}
SEEDS=${SEEDS:-5}
LR=${LR:-5e-5}
REPEATS=${REPEATS:-3}
OUT=${OUT:-docs/results/tracks}
PY=${PYTHON:-python}
files=()
for ((s = 0; s < SEEDS; s++)); do
  echo "== seed $s $(date +%T)"
  "$PY" benchmarks/real_tracks.py --run "$WORK/runs/s3k-seed$s" --data "$WORK/crop" \
    --calibration "$WORK/calibration_fixed.toml" --recording "$D" --work "$WORK/tracks/seed$s" \
    --loop --control --lr "$LR" --repeats "$REPEATS" --out "$OUT/real-seed$s.json"
  files+=("$OUT/real-seed$s.json")
done
"$PY" benchmarks/real_tracks_seeds.py "${files[@]}" --out "$OUT/real-seeds.json"
