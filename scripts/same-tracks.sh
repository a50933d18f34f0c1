#!/usr/bin/env bash
# Does `s3k track` write the same files as at an earlier revision? Tracks the real recording with RUN twice,
# once with this checkout's s3k and once with REVISION's (a `git archive` of it in a temporary folder), with
# the same options, and compares every file byte for byte; exits 1 when one differs.
#
#   bash scripts/same-tracks.sh REVISION RUN CALIBRATION [RECORDING_DIR] [-- more s3k track options]
#
# e.g. bash scripts/same-tracks.sh e36f624 /tmp/real-held/runs/s3k-seed0 /tmp/real-held/calibration_fixed.toml \
#        -- --min-weight 0.5
set -euo pipefail
cd "$(dirname "$0")/.."
REV=$1 RUN=$(realpath "$2") CAL=$(realpath "$3"); shift 3
D=../shared/data/real/sleap-anipose-minimal_session/minimal_session
if [ $# -gt 0 ] && [ "$1" != -- ]; then D=$1; shift; fi
[ $# -gt 0 ] && [ "$1" = -- ] && shift
D=$(realpath "$D")
. scripts/real-recording.sh  # videos
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
git archive "$REV" | tar -x -C "$work" --one-top-level=src
for side in then now; do
  src=$PWD; [ "$side" = then ] && src=$work/src
  mkdir -p "$work/$side"
  (cd "$work/$side" && PYTHONPATH=$src OMP_NUM_THREADS=1 python -m s3k.cli track "$RUN" --videos "${videos[@]}" \
    --calibration "$CAL" --out tracked.csv --no-progress "$@" > log.txt 2>&1) || { cat "$work/$side/log.txt"; exit 2; }
done
echo "s3k track of $(basename "$D") with $RUN: $REV against $(git rev-parse --short HEAD)$(git diff --quiet || echo +modified)"
status=0
for f in $(cd "$work/then" && ls | grep -v '^log.txt$'); do
  if cmp -s "$work/then/$f" "$work/now/$f"; then echo "  $f: identical"; else echo "  $f: DIFFERS"; status=1; fi
done
[ "$(cd "$work/then" && ls | sort)" = "$(cd "$work/now" && ls | sort)" ] || { echo "  the files written differ"; status=1; }
exit $status
