# s3k calibrate and s3k check-calibration: boards out of range, camera names that are paths, outputs over the
# command's own inputs, a repair worse than the calibration, the same images for several cameras.
# In $LOOSE_WORK/cal: a good rig's board images, board.toml, calibration.toml, a labelled dataset ds,
# boards out of range, calibrations naming a camera ../escape or p<newline>q, a detector run of cameras
# ../escape, q, r.
calibration_setup() {
    CAL=$LOOSE_WORK/cal
    [ -d "$CAL/ds" ] && return
    python - "$CAL" <<'PY'
import sys
from pathlib import Path

sys.path.insert(0, "tests")
from helpers.charuco import write_recalibration_case  # the tests' board, drawn with OpenCV
from helpers.tiny_detector import save_run

from s3k.detector import DetectorMeta
from s3k.model import UNetConfig

cal = Path(sys.argv[1])
write_recalibration_case(cal, broken=False)
base = {"board_x": "5", "board_y": "7", "square_length": "30", "marker_length": "22"}
for name, fields in {"zero": {"board_x": "0", "board_y": "0"},
                     "huge": {"board_x": "99999", "board_y": "99999"}, "nan": {"board_x": "nan"},
                     "eight": {"board_x": '"eight"'},
                     "marker": {"marker_length": "40"}, "negative": {"square_length": "-30"},
                     "inf": {"square_length": "inf"}, "swapped": {"board_x": "7", "board_y": "5"}}.items():
    (cal / f"{name}.toml").write_text("".join(f"{k} = {v}\n" for k, v in {**base, **fields}.items()))
text = (cal / "calibration.toml").read_text()
(cal / "escape.toml").write_text(text.replace('name = "p"', 'name = "../escape"'))
(cal / "newline.toml").write_text(text.replace('name = "p"', 'name = "p\\nq"'))
meta = DetectorMeta(keypoints=["a", "b", "c", "d"], cameras=["../escape", "q", "r"], image_size=(32, 32),
                    stride=2, sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1).to_dict())
save_run(cal / "run", meta, seed=0)
PY
}
calibration_setup
IMG=$CAL/images
SRC=("p=$IMG/p-*.png" "q=$IMG/q-*.png" "r=$IMG/r-*.png")
BOARD=(--squares 5x7 --square-length 30 --marker-length 22)
CHARUCO=(--charuco "p=$IMG/p-*.png" "q=$IMG/q-*.png" "r=$IMG/r-*.png")

refuse calibrate-squares-0x0 'squares along x must be a whole number from 2 to 100, got 0' -- \
    s3k calibrate "${SRC[@]}" --squares 0x0 --square-length 30 --marker-length 22 --out c.toml
refuse calibrate-squares-huge 'squares along x must be a whole number from 2 to 100, got 99999' -- \
    s3k calibrate "${SRC[@]}" --squares 99999x99999 --square-length 30 --marker-length 22 --out c.toml
refuse calibrate-squares-eight "squares along x must be a whole number .* got 'eight'" -- \
    s3k calibrate "${SRC[@]}" --squares eightx7 --square-length 30 --marker-length 22 --out c.toml
refuse calibrate-marker-larger 'marker-length must be a length from 0 up to .* 30, got 40' -- \
    s3k calibrate "${SRC[@]}" --squares 5x7 --square-length 30 --marker-length 40 --out c.toml
for b in zero:board_x huge:board_x nan:board_x eight:board_x marker:marker_length negative:square_length \
         inf:square_length; do
    refuse "calibrate-board-${b%%:*}" "${b%%:*}.toml: ${b#*:} must be" -- \
        s3k calibrate "${SRC[@]}" --board "$CAL/${b%%:*}.toml" --out c.toml
    refuse "check-calibration-board-${b%%:*}" "${b%%:*}.toml: ${b#*:} must be" -- \
        s3k check-calibration "$CAL/ds" --recalibrate q --board "$CAL/${b%%:*}.toml" "${CHARUCO[@]}"
done
refuse calibrate-board-swapped 'no ChArUco corners .* check the board' -- \
    s3k calibrate "${SRC[@]}" --board "$CAL/swapped.toml" --out c.toml
refuse check-calibration-board-swapped 'no ChArUco corners .* check the board' -- \
    s3k check-calibration "$CAL/ds" --recalibrate q --board "$CAL/swapped.toml" "${CHARUCO[@]}"

refuse calibrate-camera-escape "camera name '\.\./escape' holds '/'" -- \
    s3k calibrate "../escape=$IMG/p-*.png" "q=$IMG/q-*.png" "${BOARD[@]}" --out c.toml
refuse calibrate-camera-newline "camera name 'a\\\\nb' holds '\\\\n'" -- \
    s3k calibrate "$(printf 'a\nb')=$IMG/p-*.png" "q=$IMG/q-*.png" "${BOARD[@]}" --out c.toml
refuse import-camera-escape "camera name '\.\./escape' holds '/'" -- \
    s3k import --calibration "$CAL/escape.toml" --videos "../escape=$IMG/p-*.png" "q=$IMG/q-*.png" \
    --keypoints a --out ds
refuse check-calibration-toml-newline "newline.toml: \[cam_0\] name: camera name 'p\\\\nq'" -- \
    s3k check-calibration "$CAL/ds" --recalibrate q --calibration "$CAL/newline.toml" "${CHARUCO[@]}"
refuse track-overlay-escape "camera name '\.\./escape' holds '/'" -- \
    bash -c 'mkdir -p o && echo mine > escape.mp4 && s3k track "$0/run" --videos "../escape=$1/p-*.png" \
    "q=$1/q-*.png" "r=$1/r-*.png" --calibration "$0/escape.toml" --overlay o --out t.csv' "$CAL" "$IMG"

refuse calibrate-out-on-board-image "--out .* is this command's input \(CAM=SOURCE" -- \
    bash -c 'cp "$0"/p-*.png . && s3k calibrate "p=p-*.png" "q=$0/q-*.png" "r=$0/r-*.png" \
    --squares 5x7 --square-length 30 --marker-length 22 --out p-3.png --overwrite' "$IMG"
accept calibrate-out-on-board-image-kept 'cmp -s p-3.png "$IMG/p-3.png"' -- \
    bash -c 'cp "$0"/p-*.png . && s3k calibrate "p=p-*.png" "q=$0/q-*.png" "r=$0/r-*.png" \
    --squares 5x7 --square-length 30 --marker-length 22 --out p-3.png --overwrite; true' "$IMG"
refuse calibrate-out-on-labels "--out .* is this command's input \(--labels" -- \
    bash -c 'echo x > l.h5 && s3k calibrate "$@" --out l.h5 --overwrite --labels p=l.h5' \
    "${SRC[@]}" "${BOARD[@]}"
refuse calibrate-same-images "cameras w, x, y, z are given the same source" -- \
    s3k calibrate "w=$IMG/p-*.png" "x=$IMG/p-*.png" "y=$IMG/p-*.png" "z=$IMG/p-*.png" "${BOARD[@]}" \
    --out c.toml
refuse calibrate-copied-images "cameras a, b show identical board views" -- \
    bash -c 'mkdir a b && cp "$0"/p-*.png a && cp "$0"/p-*.png b && s3k calibrate a=a b=b "r=$0/r-*.png" \
    --squares 5x7 --square-length 30 --marker-length 22 --out c.toml' "$IMG"
refuse calibrate-labels-unknown-camera "--labels: camera 'z' is not calibrated here" -- \
    s3k calibrate "${SRC[@]}" "${BOARD[@]}" --out c.toml --labels z=x.h5
accept calibrate-good 'test -s c.toml' -- s3k calibrate "${SRC[@]}" "${BOARD[@]}" --out c.toml

refuse check-calibration-worse-repair "median residual .* \(camera q: .*nothing written" -- \
    s3k check-calibration "$CAL/ds" --recalibrate q --charuco "p=$IMG/p-*.png" "q=$IMG/p-*.png" \
    "r=$IMG/r-*.png" --write-calibration fixed.toml
accept check-calibration-worse-repair-forced 'test -s fixed.toml && grep -q "kept: --force" .stderr' -- \
    bash -c 's3k check-calibration "$0/ds" --recalibrate q --charuco "p=$1/p-*.png" "q=$1/p-*.png" \
    "r=$1/r-*.png" --write-calibration fixed.toml --force; [ $? = 2 ]' "$CAL" "$IMG"  # 2: q inconsistent
accept check-calibration-good-repair 'test -s fixed.toml' -- \
    s3k check-calibration "$CAL/ds" --recalibrate q "${CHARUCO[@]}" --write-calibration fixed.toml
