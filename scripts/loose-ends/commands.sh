# The newer commands' loose ends: track's and stream's filter options, add-frames' ranking and the record
# beside a track, label --public-url and train --resume --preset. Sourced by scripts/loose-ends.sh.

# Once per run: the tiny rig of tests/helpers/track_rig.py (three cameras, 64 x 48 px videos of three moving dots, an
# anipose calibration), an untrained tiny detector saved as a run folder (no rigid layout), its track with the
# ranking and record beside it, and a dataset of three of the videos' frames to add frames to (a few seconds).
commands_setup() {
    C=$LOOSE_WORK/commands
    [ -f "$C/ready" ] && return 0
    mkdir -p "$C/track"
    PYTHONPATH="$PWD/tests${PYTHONPATH:+:$PYTHONPATH}" python - "$C" <<'EOF' >"$C/setup.log" 2>&1 || return 1
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from helpers.track_rig import CAMERAS, COLOURS, FRAMES, KEYPOINTS, VIDEO_SIZE, make_rig, moving_points, track_run

from s3k.data import DatasetWriter
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.video import write_video
from s3k.geometry import project

root = Path(sys.argv[1])
rig = make_rig()
write_anipose_calibration(root / "calibration.toml", rig)
uv, _ = project(rig.cameras[None], torch.as_tensor(moving_points(FRAMES))[:, None])
W, H = VIDEO_SIZE
frames = {}
for c, cam in enumerate(CAMERAS):
    frames[cam] = []
    for f in range(FRAMES):
        img = np.full((H, W, 3), 80, np.uint8)
        for k in range(len(KEYPOINTS)):
            centre = tuple(int(round(float(v) * 4)) for v in uv[f, c, k])
            cv2.circle(img, centre, 10, COLOURS[k], -1, cv2.LINE_AA, shift=2)
        frames[cam].append(img)
    write_video(root / f"{cam}.mp4", frames[cam], fps=25)
track_run(root / "run")
with DatasetWriter(root / "data", KEYPOINTS, CAMERAS, (W, H), units="mm", calibration=rig.cameras) as w:
    for f, split in enumerate(["labelled", "test", "unlabelled"]):
        images = np.stack([frames[cam][f] for cam in CAMERAS])
        labels = np.full((len(CAMERAS), len(KEYPOINTS), 2), 20.0) if split != "unlabelled" else None
        w.add_frame(f, split, images, labels=labels, extra={"video_frame": f})
EOF
    s3k track "$C/run" --calibration "$C/calibration.toml" --out "$C/track/points3d.csv" --no-progress \
        --min-weight 0 --videos left="$C/left.mp4" top="$C/top.mp4" right="$C/right.mp4" \
        >>"$C/setup.log" 2>&1 || return 1
    touch "$C/ready"
}

# track with COMMAND's options; the CSV goes into the case folder
track() { s3k track "$C/run" --calibration "$C/calibration.toml" --out points3d.csv --no-progress \
    --videos left="$C/left.mp4" top="$C/top.mp4" right="$C/right.mp4" "$@"; }
# a copy of the track and of the dataset in the case folder, EDIT (a shell snippet) run on them, then
# add-frames
add_frames() {
    cp "$C"/track/points3d* . && cp -r "$C/data" data && eval "$1" &&
        s3k add-frames points3d.csv --data data --worst 2
}
# a request to the label app behind --public-url PUBLIC from a page at ORIGIN, the Host the proxy forwards;
# prints the status
label_request() {
    python - "$C/data" "$@" <<'EOF'
import sys
import warnings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from s3k.label.server import create_app

data, public, origin, host = sys.argv[1:]
client = TestClient(create_app(data, public_url=public), base_url="http://127.0.0.1:8765")
version = client.get("/api/frame/2").json()["version"]
r = client.post("/api/frame/2/label", json={"version": version, "edits": [
    {"camera": "left", "keypoint": "nose", "u": 20.0, "v": 30.0}]}, headers={"Origin": origin, "Host": host})
print(r.status_code)
EOF
}

if ! commands_setup; then
    _loose_verdict "set-up" 0 "the tiny recording, run and track were not made: $(tail -n 3 "$C/setup.log")"
else
    # track / stream: every filter option in a range, refused as the command line is parsed
    refuse track-gate-overflow 'argument --filter-gate: must be in \[0, 100\]' -- track --filter-gate 1e308
    refuse track-process-noise-overflow 'argument --filter-process-noise: must be in' -- \
        track --filter-process-noise 1e308
    refuse track-layout-std-underflow 'argument --filter-layout-std: must be in' -- \
        track --filter-layout-std 1e-200
    refuse stream-gate-overflow 'argument --filter-gate: must be in' -- \
        s3k stream "$C/run" --calibration "$C/calibration.toml" --sources left=0 top=1 --filter kalman \
        --filter-gate 1e308
    accept track-gate-at-its-bound \
        'test -s points3d.csv && grep -qE "\"gate\": 100(\.0)?," points3d.csv.s3k.json' -- \
        track --filter-gate 100
    refuse track-rigid-on-without-layout \
        '--filter-rigid on: the run .* has no rigid layout.*--layout-tol.*--filter-rigid auto or off' -- \
        track --filter-rigid on
    accept track-rigid-auto-without-layout 'test -s points3d.csv' -- track --filter-rigid auto

    # add-frames: the ranking and the record beside the track
    refuse add-frames-rank-not-a-number 'points3d.doubt.csv: line 2: rank .x. is not a whole number' -- \
        add_frames "sed -i '2s/^1,/x,/' points3d.doubt.csv"
    refuse add-frames-negative-frame 'points3d.doubt.csv: line 2: fnum .-3. is not a whole number >= 0' -- \
        add_frames "sed -i -E '2s/^1,[0-9]+,/1,-3,/' points3d.doubt.csv"
    refuse add-frames-ranking-outside-its-folder "s3k.json: broken, 'doubt' is '../x.doubt.csv'" -- \
        add_frames "sed -i 's|\"doubt\": \"points3d.doubt.csv\"|\"doubt\": \"../x.doubt.csv\"|' \
            points3d.csv.s3k.json"
    refuse add-frames-broken-record 'points3d.csv.s3k.json: broken, not JSON' -- \
        add_frames "echo '{\"units\": ' > points3d.csv.s3k.json"
    refuse add-frames-record-of-wrong-types "points3d.csv.s3k.json: broken, 'videos' is \[" -- \
        add_frames "echo '{\"units\": \"mm\", \"videos\": [\"left.mp4\"]}' > points3d.csv.s3k.json"
    accept add-frames-as-tracked '[ "$(wc -l < data/label-queue.csv)" = 3 ]' -- add_frames true

    # label --public-url
    refuse label-malformed-public-url "--public-url 'http://\[::1': expected http\(s\)://HOST" -- \
        s3k label "$C/data" --public-url 'http://[::1'
    accept label-public-http-twin-refused 'grep -qx 403 .stdout' -- \
        label_request https://labels.example.org http://labels.example.org labels.example.org
    accept label-public-origin-taken 'grep -qx 200 .stdout' -- \
        label_request https://labels.example.org https://labels.example.org labels.example.org
    accept label-public-default-port 'grep -qx 200 .stdout' -- \
        label_request https://labels.example.org:443 https://labels.example.org labels.example.org

    # train --resume with a preset that is not the run's configuration
    refuse train-resume-other-preset \
        '--resume: --preset box-fast sets .* but the run in .* was trained with' -- \
        s3k train "$C/data" --out "$C/run" --resume --preset box-fast
fi
