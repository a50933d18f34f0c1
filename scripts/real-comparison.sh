#!/usr/bin/env bash
# S3K against labels only on the real recording, over several seeds: the import of scripts/real-example.sh
# (shipped calibration -> recalibrate the defective camera -> crop around the arena) done once, then one
# training at a time, S3K and the labels-only baseline (--no-unsup) for seed 0, then seed 1, ...
#
#   bash scripts/real-comparison.sh [RECORDING_DIR]
#
# $WORK (default /tmp/real-work): dataset $WORK/crop, runs $WORK/runs/{s3k,baseline}-seedN. $SEEDS (default
# 5), $STEPS (3000), $THREADS (1), $SCALE (the arena crops' import scale, 0.25: 128 px), $TRAIN_OPTIONS (more
# `s3k train` options for both models, e.g. '--preset box-headline --layout-tol 0' with SCALE=0.5), $TEST_FRAMES
# (random, as the committed figures; blocks: the test frames held out in time; last: the recording's end held
# out, $MARGIN frames after the last labelled one; scripts/real-recording.sh), $CROPS
# (hand: the boxes of scripts/real-recording.sh; auto: found by `s3k crops` after a brief labels-only pass on
# whole frames, as docs/real-example.md shows), $MODELS (default 's3k baseline': which of the two to train).
# Resumable: run it again and it skips what is done and resumes a run that
# was cut short (s3k train --resume). Trainings run under `nice -n 10`. Evaluate and compare with
# benchmarks/real_comparison.py.
set -euo pipefail
cd "$(dirname "$0")/.."
D=$(realpath "${1:-../shared/data/real/sleap-anipose-minimal_session/minimal_session}")
WORK=${WORK:-/tmp/real-work}
SEEDS=${SEEDS:-5}
STEPS=${STEPS:-3000}
THREADS=${THREADS:-1}
SCALE=${SCALE:-0.25}
read -r -a TRAIN_OPTS <<< "${TRAIN_OPTIONS:-}"
PY=${PYTHON:-python}
s3k() { "$PY" -m s3k.cli "$@"; }
mkdir -p "$WORK/runs"
. scripts/real-recording.sh  # cams, videos, sleap, crops, split

if [ ! -f "$WORK/crop/s3k.json" ]; then
  echo "== import $(date +%T)"
  rm -rf "$WORK/shipped" "$WORK/crop.tmp"
  s3k import --calibration "$D/calibration.toml" --videos "${videos[@]}" --sleap "${sleap[@]}" "${split[@]}" \
    --scale 0.25 --out "$WORK/shipped"
  status=0
  s3k check-calibration "$WORK/shipped" --recalibrate flagged --write-calibration "$WORK/calibration_fixed.toml" \
    > "$WORK/check-calibration.txt" || status=$?
  [ "$status" -le 2 ] || exit "$status"
  if [ "${CROPS:-hand}" = auto ]; then  # the boxes from a brief labels-only pass over whole frames
    rm -rf "$WORK/whole" "$WORK/run-whole"
    s3k import --calibration "$WORK/calibration_fixed.toml" --videos "${videos[@]}" --sleap "${sleap[@]}" \
      "${split[@]}" --scale 0.25 --out "$WORK/whole"
    nice -n 10 "$PY" -m s3k.cli train "$WORK/whole" --out "$WORK/run-whole" --image-size 96 --steps 1000 \
      --no-unsup --threads "$THREADS" --no-progress
    read -r -a crops <<< "$(s3k crops "$WORK/run-whole" --data "$WORK/whole" --out "$WORK/crops.json")"
    crops=("${crops[@]:1}")  # the boxes, without the leading --crop
  fi
  s3k import --calibration "$WORK/calibration_fixed.toml" --videos "${videos[@]}" --sleap "${sleap[@]}" \
    "${split[@]}" --scale "$SCALE" --crop "${crops[@]}" --out "$WORK/crop.tmp"
  mv "$WORK/crop.tmp" "$WORK/crop"
fi

train() {  # train RUN [options]: new, resumed, or (finished) returns at once
  local run=$1; shift
  echo "== $(basename "$run") start $(date +%T)"
  if [ -f "$run/config.json" ] || [ -f "$run/two_pass_options.json" ]; then
    nice -n 10 "$PY" -m s3k.cli train "$WORK/crop" --out "$run" --resume --threads "$THREADS" --no-progress
  else
    nice -n 10 "$PY" -m s3k.cli train "$WORK/crop" --out "$run" --steps "$STEPS" --threads "$THREADS" \
      --no-progress ${TRAIN_OPTS[@]+"${TRAIN_OPTS[@]}"} "$@"
  fi
  echo "== $(basename "$run") end $(date +%T)"
}
read -r -a MODELS <<< "${MODELS:-s3k baseline}"
for ((s = 0; s < SEEDS; s++)); do
  for m in "${MODELS[@]}"; do
    case $m in
      s3k) train "$WORK/runs/s3k-seed$s" --seed "$s" ;;
      baseline) train "$WORK/runs/baseline-seed$s" --seed "$s" --no-unsup ;;
      *) echo "MODELS: '$m' is neither s3k nor baseline" >&2; exit 2 ;;
    esac
  done
done
echo "== all done $(date +%T)"
