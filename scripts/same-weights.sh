#!/usr/bin/env bash
# Does `s3k train` train the same weights as at an earlier revision? Renders a tiny box dataset once, trains it
# with the same seed at REVISION (a `git archive` of it in a temporary folder) and at this checkout, one pass,
# two, and the box headline's preset (--preset box-headline, its passes cut to STEPS), and compares the sha256 of every model.pt's tensors; exits 1 when one differs.
#
#   bash scripts/same-weights.sh REVISION [STEPS]
set -euo pipefail
cd "$(dirname "$0")/.."
REV=$1 STEPS=${2:-30}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
git archive "$REV" | tar -x -C "$work" --one-top-level=src
export MUJOCO_GL=${MUJOCO_GL:-osmesa} PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-osmesa} OMP_NUM_THREADS=1
PYTHONPATH=$PWD python -m s3k.cli simulate box --out "$work/box" --size 64 --labelled 6 --unlabelled 16 --test 6 \
  --workers 1 > /dev/null 2>&1
hash() {  # hash RUN: sha256 of the tensors of every model.pt under RUN (names and bytes, sorted)
  PYTHONPATH=$PWD python - "$1" <<'PY'
import hashlib, sys
from pathlib import Path
import torch
for path in sorted(Path(sys.argv[1]).rglob("model.pt")):
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = state.get("model", state)
    h = hashlib.sha256()
    for name in sorted(state):
        h.update(name.encode()); h.update(state[name].cpu().contiguous().numpy().tobytes())
    print(path.relative_to(sys.argv[1]), h.hexdigest())
PY
}
status=0
for kind in one two preset; do
  opts=(--steps "$STEPS" --seed 0 --threads 1 --val-every 10 --no-progress)
  [ "$kind" = two ] && opts+=(--two-pass --coarse-size 48 --crop-size 48)
  [ "$kind" = preset ] && opts+=(--preset box-headline --coarse-steps "$STEPS")
  for side in then now; do
    src=$PWD; [ "$side" = then ] && src=$work/src
    (cd "$src" && PYTHONPATH=$src python -m s3k.cli train "$work/box" --out "$work/$kind-$side" "${opts[@]}" \
      > "$work/$kind-$side.log" 2>&1) || { cat "$work/$kind-$side.log"; exit 2; }
  done
  a=$(hash "$work/$kind-then") b=$(hash "$work/$kind-now")
  echo "$kind ($STEPS steps a pass), seed 0: $REV against $(git rev-parse --short HEAD)$(git diff --quiet || echo +modified)"
  echo "$b" | sed 's/^/  /'
  if [ "$a" = "$b" ]; then echo "  identical"; else echo "  DIFFERENT; $REV gave:"; echo "$a" | sed 's/^/  /'; status=1; fi
done
exit $status
