# The real recording's files and the example's choices, shared by scripts/real-example.sh and
# scripts/real-comparison.sh (sourced, with $D the recording folder): per camera its video and proofread SLEAP
# file, 512x512 boxes (full-resolution pixels) around each camera's arena floor (x0.25 gives 128x128 images at
# the pixel scale of a plain --scale 0.25 import), and the labelled/test split (drawn at random, as when the
# committed figures were measured: test frames between the labelled ones, not a held-out stretch).
cams=(back mid side top)
videos=() sleap=()
for c in "${cams[@]}"; do
  videos+=("$c=$D/$c/minimal_$c.mp4")
  sleap+=("$c=$D/$c/minimal_${c}_proofread.analysis.h5")
done
crops=(back=610,350,1122,862 mid=246,374,758,886 side=328,406,840,918 top=266,330,778,842)
# $TEST_FRAMES=blocks holds the 40 test frames out in time instead: one contiguous block, no labelled frame within
# --margin (10) frames of it.
# $TEST_FRAMES=last holds out the last 40 (frames 80-119), the labelled frames before them ($MARGIN frames away).
split=(--labelled 10 --test 40 --seed 0 --test-frames "${TEST_FRAMES:-random}" ${MARGIN:+--margin "$MARGIN"})
