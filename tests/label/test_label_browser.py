"""The labelling page driven in a headless Chromium (Playwright, Debian's /usr/bin/chromium) against a server
started here on a free port, over a small generated dataset whose true projections are known.

With ``S3K_SCREENSHOTS=DIR`` set, a last test photographs the page on the simulated box scene into DIR
(``docs/img`` for docs/labelling.md; ``S3K_LABEL_RUN=RUN`` adds a trained run's suggestions).
"""

from __future__ import annotations

import csv
import os
import shutil
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers.label_data import FAR_PX, NEAR_PX, label_true_projections, make_label_dataset
from helpers.synthetic_rig import CAMERAS

CHROMIUM = "/usr/bin/chromium"
if shutil.which(CHROMIUM) is None:
    pytest.skip(f"no Chromium at {CHROMIUM} (scripts/setup.sh installs Debian's chromium)",
                allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api")
uvicorn = pytest.importorskip("uvicorn")

from s3k.data import Dataset  # noqa: E402
from s3k.label.server import create_app  # noqa: E402
from s3k.label.store import LabelStore  # noqa: E402

SHOTS = os.environ.get("S3K_SCREENSHOTS")


class Server:
    """The app on a free loopback port, in a thread of this process."""

    def __init__(self, data: Path, run: Path | None = None, record: list | None = None) -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.app = app = create_app(data, run)
        if record is not None:  # every answer's (method, path, status), as the server sent it
            app = recording(app, record)
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> str:
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            assert time.monotonic() < deadline and self.thread.is_alive(), "server did not start"
            time.sleep(0.02)
        return f"http://127.0.0.1:{self.port}/"

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


def recording(app, log: list):
    async def recorded(scope, receive, send):
        async def sent(message):
            if message["type"] == "http.response.start":
                log.append((scope["method"], scope["path"], message["status"]))
            await send(message)

        await app(scope, receive, sent if scope["type"] == "http" else send)

    return recorded


@pytest.fixture
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        try:
            yield b
        finally:
            b.close()


def shot(page, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        bottom = page.evaluate("Math.ceil(document.querySelector('#views').getBoundingClientRect().bottom)")
        width = page.viewport_size["width"]
        clip = {"x": 0, "y": 0, "width": width, "height": bottom + 8}
        page.screenshot(path=str(Path(SHOTS) / name), clip=clip)


def page_xy(page, camera: str, uv) -> tuple[float, float]:
    x, y = page.evaluate("([c, u, v]) => s3kLabel.toClient(c, u, v)", [camera, float(uv[0]), float(uv[1])])
    return x, y


def wait_version(page, version: int) -> None:
    page.wait_for_function(f"document.body.dataset.version === '{version}'")
    page.wait_for_function("document.getElementById('status').className === 'saved'")


def polyline(page, camera: str, keypoint: str) -> np.ndarray:
    text = page.get_attribute(f".view[data-camera={camera}] polyline.epipolar[data-keypoint={keypoint}]",
                              "points")
    return np.array([[float(x) for x in p.split(",")] for p in text.split()])


def distance_to(points: np.ndarray, p) -> float:
    a, b = points[:-1], points[1:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    return float(np.linalg.norm(a + t[:, None] * ab - p, axis=-1).min())


def reproj_centre(page, camera: str, keypoint: str) -> np.ndarray:
    rect = page.locator(f".view[data-camera={camera}] rect.reproj[data-keypoint={keypoint}]")
    x, y, w = (float(rect.get_attribute(a)) for a in ("x", "y", "width"))
    return np.array([x + w / 2, y + w / 2])



def open_app(browser, url: str, width: int, height: int):
    """A page of the app at ``url`` once it is ready, and the list its script errors go to."""
    page = browser.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector("body[data-ready='1']")
    return page, errors

def test_label_by_clicking_in_two_views(tmp_path, browser):
    truth = make_label_dataset(tmp_path / "ds", size=96)
    uv = truth.uv(4)
    with Server(truth.path) as url:
        page, errors = open_app(browser, url, 1500, 720)
        assert page.locator(".view svg").count() == 4  # every view of the frame
        for _ in range(4):  # keyboard: to frame 4
            page.keyboard.press("ArrowRight")
        page.wait_for_function("document.body.dataset.frame === '4'")
        assert page.inner_text("#keypoints li.current .name") == "a"
        page.keyboard.press("ArrowDown")
        assert page.inner_text("#keypoints li.current .name") == "b"
        page.keyboard.press("ArrowUp")
        assert page.inner_text("#keypoints li.current .name") == "a"

        # one view: the epipolar line of the click in the others, through the true projections
        page.mouse.click(*page_xy(page, "cam0", uv[0, 0]))
        wait_version(page, 1)
        for c in (1, 2, 3):
            assert distance_to(polyline(page, CAMERAS[c], "a"), uv[c, 0]) < 0.6
        assert page.locator(".view[data-camera=cam0] polyline.epipolar").count() == 0

        # a second view: triangulated and reprojected into every view, with residuals
        page.mouse.click(*page_xy(page, "cam1", uv[1, 0]))
        wait_version(page, 2)
        assert page.locator("polyline.epipolar").count() == 0
        for c in (2, 3):
            np.testing.assert_allclose(reproj_centre(page, CAMERAS[c], "a"), uv[c, 0], atol=1.0)
        assert page.inner_text(".view[data-camera=cam0] .residual").endswith(" px")
        state = page.evaluate("s3kLabel.app.frame")
        np.testing.assert_allclose(state["geometry"]["a"]["point"], truth.points[4, 0], atol=3e-3)

        # zoomed in, a click lands where it is aimed, closer than a screen pixel of the full view
        cam3 = page.locator(".view[data-camera=cam3] svg")
        page.mouse.move(*page_xy(page, "cam3", uv[3, 0]))
        for _ in range(8):
            page.mouse.wheel(0, -100)
        page.wait_for_function("s3kLabel.app.views.cam3.box[2] < 40")
        assert float(cam3.get_attribute("viewBox").split()[2]) < 40
        page.mouse.click(*page_xy(page, "cam3", uv[3, 0]))
        wait_version(page, 3)
        page.keyboard.press("0")  # reset zoom

        # "not visible": the key x over a view, and the view's button
        page.mouse.move(*page_xy(page, "cam2", (5, 5)))
        page.keyboard.press("x")
        wait_version(page, 4)
        page.locator("#keypoints li[data-keypoint=b]").click()
        page.locator(".view[data-camera=cam1] button.occlude").click()
        wait_version(page, 5)

        # drag a point to correct it
        page.locator("#keypoints li[data-keypoint=a]").click()
        start = page_xy(page, "cam1", uv[1, 0])
        target = page_xy(page, "cam1", uv[1, 0] + [4.0, 3.0])
        page.mouse.move(*start)
        page.mouse.down()
        page.mouse.move((start[0] + target[0]) / 2, (start[1] + target[1]) / 2)
        page.mouse.move(*target)
        page.mouse.up()
        wait_version(page, 6)

        # brightness
        page.locator("#brightness").fill("2")
        assert "brightness(2)" in page.get_attribute(".view[data-camera=cam0] image", "style")
        assert errors == []

    # what is on disk
    ds = Dataset.open(truth.path)
    got, mask = ds.labels([4])
    assert mask[0, :, 0].tolist() == [True, True, False, True]
    np.testing.assert_allclose(got[0, 0, 0], uv[0, 0], atol=0.4)
    np.testing.assert_allclose(got[0, 3, 0], uv[3, 0], atol=0.1)  # clicked zoomed in
    np.testing.assert_allclose(got[0, 1, 0], uv[1, 0] + [4.0, 3.0], atol=0.4)  # dragged
    with open(truth.path / "labels.csv") as f:
        rows = {(r["camera"], r["keypoint"]): r for r in csv.DictReader(f)}
    assert rows[("cam2", "a")]["visible"] == "0" and rows[("cam1", "b")]["visible"] == "0"
    sources = [e["source"] for e in LabelStore.open(truth.path).history(4)]
    assert sources == ["click", "click", "click", "not visible", "not visible", "drag"]


def test_a_click_labels_the_selected_keypoint_beside_another_marker_undo_and_locked_test_frames(tmp_path,
                                                                                                   browser):
    """Markers of two keypoints 3 screen pixels apart: a click on one with the other selected places the
    selected one; Ctrl+Z puts it back; Shift+click selects; a test frame takes no click until unlocked."""
    from s3k.label.store import Edit

    truth = make_label_dataset(tmp_path / "ds", size=96)
    LabelStore.open(truth.path).save(4, [Edit("cam0", "a", 40.0, 40.0), Edit("cam0", "b", 41.0, 40.0)], None)
    with Server(truth.path) as url:
        page = browser.new_page(viewport={"width": 1500, "height": 720})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "?frame=4")
        page.wait_for_selector("body[data-ready='1']")
        at_a, at_b = page_xy(page, "cam0", (40.0, 40.0)), page_xy(page, "cam0", (41.0, 40.0))
        assert 2.0 < np.hypot(at_a[0] - at_b[0], at_a[1] - at_b[1]) < 4.0  # 3 screen pixels apart
        assert page.inner_text("#keypoints li.current .name") == "a"
        page.mouse.click(*at_b)  # on b's marker, with a selected
        wait_version(page, 2)
        assert page.inner_text("#keypoints li.current .name") == "a"
        got = {lab["keypoint"]: (lab["u"], lab["v"]) for lab in page.evaluate("s3kLabel.app.frame.labels")}
        np.testing.assert_allclose(got["a"], (41.0, 40.0), atol=0.2)  # a placed where clicked
        assert got["b"] == (41.0, 40.0)  # b untouched
        page.keyboard.press("Control+z")
        wait_version(page, 3)
        got = {lab["keypoint"]: (lab["u"], lab["v"]) for lab in page.evaluate("s3kLabel.app.frame.labels")}
        assert got == {"a": (40.0, 40.0), "b": (41.0, 40.0)}  # the state before the click
        page.keyboard.down("Shift")  # switching keypoints is explicit: Shift+click on a marker
        page.mouse.click(*at_b)
        page.keyboard.up("Shift")
        assert page.inner_text("#keypoints li.current .name") == "b"
        assert page.evaluate("document.body.dataset.version") == "3"  # nothing saved

        # frame 6 is a test frame: read-only until unlocked
        page.evaluate("s3kLabel.gotoFrame(6)")
        page.wait_for_function("document.body.dataset.frame === '6'")
        assert page.is_visible("#unlock") and page.evaluate("document.body.dataset.locked") == "1"
        page.mouse.click(*page_xy(page, "cam0", (20.0, 30.0)))
        page.wait_for_function("document.getElementById('status').className === 'error'")
        assert "read-only" in page.inner_text("#status")
        assert page.evaluate("s3kLabel.app.frame.labels") == []
        page.click("#unlock")
        page.mouse.click(*page_xy(page, "cam0", (20.0, 30.0)))
        wait_version(page, 1)
        assert errors == []
    ds = Dataset.open(truth.path)
    uv, mask = ds.labels([4, 6])
    np.testing.assert_array_equal(uv[0, 0, :2][mask[0, 0, :2]], [[40.0, 40.0], [41.0, 40.0]])
    assert mask[1].sum() == 1 and mask[1, 0, 1]  # frame 6: b, the keypoint selected by Shift+click
    np.testing.assert_allclose(uv[1, 0, 1], (20.0, 30.0), atol=0.4)


def test_accept_all_takes_only_the_views_where_the_run_is_confident(tmp_path, browser):
    """A run's suggestion in a view where its calibrated confidence is low (a hidden part) is not accepted,
    whatever its raw weight: a run trained shorter has weights far below 0.5 on views that are right."""
    import json

    truth = make_label_dataset(tmp_path / "ds", size=64)

    def with_suggestions(route):
        state = route.fetch().json()
        state["suggestions"] = {
            "a": {"cam0": {"u": 10.0, "v": 12.0, "weight": 0.05, "confidence": 0.9, "residual": 0.5},
                  "cam1": {"u": 20.0, "v": 22.0, "weight": 0.9, "confidence": 0.2, "residual": 0.0}},
            "b": {"cam2": {"u": 30.0, "v": 32.0, "weight": 0.06, "confidence": 0.6, "residual": 0.3}}}
        route.fulfill(status=200, content_type="application/json", body=json.dumps(state))

    with Server(truth.path) as url:
        page = browser.new_page()
        page.route("**/api/frame/4", with_suggestions)
        page.goto(url + "?frame=4")
        page.wait_for_selector("body[data-ready='1']")
        page.keyboard.press("Shift+A")
        wait_version(page, 1)
    uv, mask = Dataset.open(truth.path).labels([4])
    assert mask[0].sum() == 2 and mask[0, 0, 0] and mask[0, 2, 1]  # cam1 (confidence 0.2) left unlabelled
    np.testing.assert_allclose(uv[0, 0, 0], (10.0, 12.0))


def test_a_stale_tab_shows_the_newer_labels(tmp_path, browser):
    truth = make_label_dataset(tmp_path / "ds", size=64)
    with Server(truth.path) as url:
        tab1, tab2 = browser.new_page(), browser.new_page()
        for tab in (tab1, tab2):
            tab.goto(url)
            tab.wait_for_selector("body[data-ready='1']")
        tab1.mouse.click(*page_xy(tab1, "cam0", (20, 30)))
        wait_version(tab1, 1)
        tab2.mouse.click(*page_xy(tab2, "cam0", (40, 10)))
        tab2.wait_for_function("document.getElementById('status').className === 'error'")
        assert "changed since version 0" in tab2.inner_text("#status")
        assert tab2.evaluate("document.body.dataset.version") == "1"
        label = tab2.evaluate("s3kLabel.app.frame.labels[0]")
        assert (round(label["u"]), round(label["v"])) == (20, 30)


def test_a_late_answer_for_an_earlier_frame_does_not_replace_the_frame_navigated_to(tmp_path, browser):
    """Keys pressed in quick succession load several frames at once; frame 3's answer held back until frame
    4 is shown must not replace it (the next clicks would label the wrong frame)."""
    truth = make_label_dataset(tmp_path / "ds", size=64)
    with Server(truth.path) as url:
        page = browser.new_page()
        page.goto(url)
        page.wait_for_selector("body[data-ready='1']")
        held: list = []
        page.route("**/api/frame/3", lambda route: held.append(route))
        for _ in range(4):  # frames 1, 2, 3, 4 requested at once
            page.keyboard.press("ArrowRight")
        page.wait_for_function("document.body.dataset.frame === '4'")
        assert len(held) == 1  # frame 3's request waits
        with page.expect_response("**/api/frame/3"):
            held[0].continue_()
        page.wait_for_function("s3kLabel.app.loading === 0")  # every answer handled, the late one too
        assert page.evaluate("s3kLabel.app.frame.frame") == 4
        assert page.evaluate("document.body.dataset.frame") == "4"
        page.mouse.click(*page_xy(page, "cam0", (20, 30)))
        wait_version(page, 1)
    _, mask = Dataset.open(truth.path).labels([3, 4])
    assert not mask[0].any() and mask[1, 0, 0]  # the click went to frame 4


def test_frames_to_label_by_pose_coverage_and_in_proportion(tmp_path, browser):
    from helpers.synthetic_rig import KEYPOINTS
    from helpers.tiny_detector import save_run

    from s3k.detector import DetectorMeta
    from s3k.label.server import LabelApp
    from s3k.model import UNetConfig

    truth = make_label_dataset(tmp_path / "ds", size=64)
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(32, 32), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict())
    # an untrained detector whose two pose orders differ on these frames, so the page's switch shows
    run = save_run(tmp_path / "run", meta, seed=1, head_std=0.5)
    app = LabelApp(truth.path, run=run)
    want = app.suggestions.coverage(app.dataset.frames("unlabelled"), [], 1000.0)
    with Server(truth.path, run) as url:
        page = browser.new_page(viewport={"width": 1400, "height": 600})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url)
        page.wait_for_selector("#ranking li")
        page.select_option("#rank-by", "coverage")
        page.wait_for_function("document.querySelector('#ranking li').textContent.endsWith(' -')")
        items = page.locator("#ranking li")
        assert [int(items.nth(i).get_attribute("data-frame")) for i in range(items.count())] == \
            [r["frame"] for r in want]
        page.keyboard.press("n")  # the next frame of the list the page shows
        page.wait_for_function(f"document.body.dataset.frame === '{want[0]['frame']}'")
        # the representative order, loaded when picked
        rep = [r["frame"] for r in app.suggestions.coverage(app.dataset.frames("unlabelled"), [], 1000.0,
                                                             order="representative")]
        assert rep != [r["frame"] for r in want]
        page.select_option("#rank-by", "representative")
        page.wait_for_function("(want) => [...document.querySelectorAll('#ranking li')]"
                               ".map((li) => +li.dataset.frame).join() === want", arg=",".join(map(str, rep)))
        assert errors == []


@pytest.mark.skipif(not SHOTS, reason="photographs the app for docs/labelling.md: S3K_SCREENSHOTS=docs/img")
def test_screenshots_of_the_box_scene(tmp_path, browser):
    """The docs' pictures: the simulated box scene labelled in the app (and, with S3K_LABEL_RUN=RUN, a
    trained run's suggestions and ranking)."""
    pytest.importorskip("mujoco")
    import torch

    from s3k.geometry import project
    from s3k.sim.generate import SimulateConfig, simulate

    data = tmp_path / "box"
    simulate(SimulateConfig("box", size=128, labelled=0, unlabelled=6, test=0, seed=5), data, workers=1,
             progress=False)
    ds = Dataset.open(data)
    X, _ = ds.points3d([0])
    cams = ds.calibration([0], np.float64)
    uv = project(cams, torch.as_tensor(X, dtype=torch.float64)[:, None].expand(-1, 4, -1, -1))[0][0].numpy()
    with Server(data) as url:
        page = browser.new_page(viewport={"width": 1400, "height": 470})
        page.goto(url)
        page.wait_for_selector("body[data-ready='1']")
        page.locator("#keypoints li").nth(1).click()
        page.mouse.click(*page_xy(page, "cam0", uv[0, 1]))
        wait_version(page, 1)
        page.mouse.move(*page_xy(page, "cam2", uv[2, 1] + [30, 30]))
        shot(page, "label-epipolar.png")
        page.mouse.click(*page_xy(page, "cam3", uv[3, 1]))
        wait_version(page, 2)
        page.mouse.move(*page_xy(page, "cam2", uv[2, 1] + [30, 30]))
        shot(page, "label-reprojection.png")
    # the whole window at 1500x900: every keypoint labelled in two views, the skeleton joining them
    from s3k.label.skeleton import edit_skeleton
    from s3k.label.store import Edit

    K = len(ds.keypoints)
    for k in range(K):
        edit_skeleton(data, ds.keypoints, add=[ds.keypoints[k], ds.keypoints[(k + 1) % K]])
    LabelStore.open(data).save(0, [Edit(ds.cameras[c], kp, float(uv[c, k, 0]), float(uv[c, k, 1]))
                                   for k, kp in enumerate(ds.keypoints) for c in (0, 3)], None)
    with Server(data) as url:
        page = browser.new_page(viewport={"width": 1500, "height": 900})
        page.goto(url)
        page.wait_for_selector("body[data-ready='1']")
        assert page.locator(".view[data-camera=cam1] line.bone").count() == K
        shot(page, "label-window.png")
    run = os.environ.get("S3K_LABEL_RUN")
    if run:
        with Server(data, Path(run)) as url:
            page = browser.new_page(viewport={"width": 1400, "height": 470})
            page.goto(url + "?frame=3")
            page.wait_for_selector("body[data-ready='1']")
            page.wait_for_selector("#ranking li")
            shot(page, "label-suggestions.png")


ATTACK = """<!doctype html><html><body><script>
// another site's page: forms (every encoding a form has) and no-cors fetches to each state-changing route
const target = TARGET, paths = PATHS;
const body = {version: 0, edits: [{camera: "cam0", keypoint: "a", u: 5, v: 5}], first: 0, last: 3,
              overwrite: true, add: ["a", "c"], unlock: true};
const text = JSON.stringify(body);
let n = 0;
for (const path of paths) {
  for (const enctype of ["application/x-www-form-urlencoded", "multipart/form-data", "text/plain"]) {
    const name = `f${n++}`;
    const frame = document.createElement("iframe");
    frame.name = name;
    document.body.appendChild(frame);
    const form = document.createElement("form");
    Object.assign(form, {action: target + path, method: "POST", enctype, target: name});
    const input = document.createElement("input");  // text/plain sends name=value: a JSON body
    Object.assign(input, {type: "hidden", name: text.slice(0, -1) + ', "x": "', value: '"}'});
    form.appendChild(input);
    document.body.appendChild(form);
    form.submit();
  }
  fetch(target + path, {method: "POST", mode: "no-cors", body: text,
                        headers: {"Content-Type": "application/json"}}).catch(() => {});
  fetch(target + path, {method: "POST", mode: "no-cors"}).catch(() => {});
}
</script></body></html>"""


def test_a_page_of_another_origin_cannot_change_the_labels(tmp_path, browser):
    """The page of another site (another port of 127.0.0.1) submits forms and no-cors fetches to every
    state-changing route of the app: the server refuses each, and nothing in the dataset changes."""
    import http.server
    import json

    from s3k.label.propagate import propagate_labels
    from s3k.label.store import Edit

    truth = make_label_dataset(tmp_path / "ds", size=64)
    uv = truth.uv(0)
    LabelStore.open(truth.path).save(0, [Edit(CAMERAS[c], kp, float(uv[c, k, 0]), float(uv[c, k, 1]))
                                         for k, kp in enumerate(["a", "b", "c"]) for c in (0, 1)], None)
    propagate_labels(truth.path, 0, 2)  # something for /api/propagate/undo to undo
    before = {p.name: p.read_bytes() for p in sorted(truth.path.rglob("*")) if p.is_file()}
    log: list = []
    server = Server(truth.path, record=log)
    changing = {"POST", "PUT", "PATCH", "DELETE"}  # every such route of the app, a later one too
    paths = sorted({route.path.replace("{frame}", "4") for route in server.app.routes
                    if getattr(route, "methods", None) and route.methods & changing})
    assert "/api/propagate/undo" in paths and "/api/frame/4/label" in paths
    with server as url:
        page = ATTACK.replace("TARGET", json.dumps(url.rstrip("/"))).replace("PATHS", json.dumps(paths))

        class Attacker(http.server.BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's name
                self.send_response(200)
                self.send_header("Content-Type", "text/html")
                self.end_headers()
                self.wfile.write(page.encode())

            def log_message(self, *args):
                pass

        evil = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Attacker)
        threading.Thread(target=evil.serve_forever, daemon=True).start()
        try:
            tab = browser.new_page()
            tab.goto(f"http://127.0.0.1:{evil.server_address[1]}/")
            deadline = time.monotonic() + 60
            while len([e for e in log if e[0] == "POST"]) < 5 * len(paths):  # 3 forms, 2 fetches a route
                assert time.monotonic() < deadline, log
                tab.wait_for_timeout(50)
        finally:
            evil.shutdown()
    posts = [e for e in log if e[0] == "POST"]
    assert sorted({p for _, p, _ in posts}) == paths
    assert all(status in (403, 415) for _, _, status in posts), posts
    assert {p.name: p.read_bytes() for p in sorted(truth.path.rglob("*")) if p.is_file()} == before


def test_at_1500x900_the_views_fill_the_window_with_the_skeleton_drawn_and_edited(tmp_path, browser):
    """Four views in a 2x2 grid that fills the page beside the sidebar; the skeleton's edges drawn in every
    view, added and removed in the page and written to s3k.json; markers name their keypoint."""
    import json

    from s3k.label.store import Edit

    truth = make_label_dataset(tmp_path / "ds", size=96)
    uv = truth.uv(4)
    LabelStore.open(truth.path).save(4, [Edit(CAMERAS[c], kp, float(uv[c, k, 0]), float(uv[c, k, 1]))
                                         for k, kp in enumerate(["a", "b", "c"]) for c in (0, 1)], None)
    with Server(truth.path) as url:
        page = browser.new_page(viewport={"width": 1500, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "?frame=4")
        page.wait_for_selector("body[data-ready='1']")
        boxes = [page.locator(f".view[data-camera={c}]").bounding_box() for c in CAMERAS]
        assert len({round(b["x"]) for b in boxes}) == 2 and len({round(b["y"]) for b in boxes}) == 2
        grid = page.locator("#views").bounding_box()
        assert grid["y"] + grid["height"] == pytest.approx(900, abs=1)  # down to the window's bottom
        assert grid["width"] >= 1500 - 300  # all but the sidebar
        covered = sum(b["width"] * b["height"] for b in boxes) / (grid["width"] * grid["height"])
        assert covered > 0.9
        for c in CAMERAS:  # each image shown at about 4 times its 96 pixels, whole, in its view
            image = page.locator(f".view[data-camera={c}] svg > image").bounding_box()
            assert image["width"] > 350 and image["height"] > 350
            view = page.locator(f".view[data-camera={c}]").bounding_box()
            assert view["y"] <= image["y"] and image["y"] + image["height"] <= view["y"] + view["height"] + 1
        assert page.evaluate("document.scrollingElement.scrollHeight") <= 900  # nothing below the fold
        # a click still lands where it is aimed in the larger views
        page.locator("#keypoints li[data-keypoint=c]").click()
        page.mouse.click(*page_xy(page, "cam3", uv[3, 2]))
        wait_version(page, 2)
        got = [lab for lab in page.evaluate("s3kLabel.app.frame.labels") if lab["camera"] == "cam3"]
        np.testing.assert_allclose((got[0]["u"], got[0]["v"]), uv[3, 2], atol=0.3)

        # tooltips: every marker names its keypoint
        titles = page.eval_on_selector_all(".view[data-camera=cam2] [data-keypoint] > title",
                                           "ts => ts.map(t => [t.parentNode.dataset.keypoint, "
                                           "t.textContent])")
        assert {kp for kp, _ in titles} == {"a", "b", "c"}
        assert all(text.startswith(kp + ":") for kp, text in titles)

        # the skeleton: none yet; add a-b and b-c in the page, remove a-b
        assert page.locator("line.bone").count() == 0
        for a, b in (("a", "b"), ("b", "c")):
            page.select_option("#edge-a", a)
            page.select_option("#edge-b", b)
            page.click("#skeleton-add button")
            page.wait_for_selector(f"#skeleton li[data-edge='{a}-{b}']")
        assert json.loads((truth.path / "s3k.json").read_text())["skeleton"] == [["a", "b"], ["b", "c"]]
        for c in CAMERAS:  # drawn in every view, from keypoint to keypoint
            assert page.locator(f".view[data-camera={c}] line.bone").count() == 2
        bone = page.locator(".view[data-camera=cam0] line.bone[data-edge='a-b']")
        ends = [float(bone.get_attribute(k)) for k in ("x1", "y1", "x2", "y2")]
        np.testing.assert_allclose(ends, [*uv[0, 0], *uv[0, 1]], atol=1e-6)
        page.select_option("#edge-a", "c")
        page.select_option("#edge-b", "b")
        page.click("#skeleton-add button")  # c-b is b-c: refused
        page.wait_for_function("document.getElementById('status').className === 'error'")
        assert "already" in page.inner_text("#status")
        page.click("#skeleton li[data-edge='a-b'] button")
        page.wait_for_selector("#skeleton li[data-edge='a-b']", state="detached")
        assert page.locator(".view[data-camera=cam1] line.bone").count() == 1
        assert errors == []
    assert Dataset.open(truth.path).skeleton == [("b", "c")]


def test_redo_relocking_test_frames_and_accept_says_why_nothing_was_taken(tmp_path, browser):
    import json

    truth = make_label_dataset(tmp_path / "ds", size=64)

    def unsure(route):  # a run's suggestions, none confident
        state = route.fetch().json()
        state["suggestions"] = {"a": {"cam0": {"u": 10.0, "v": 12.0, "weight": 0.9, "confidence": 0.3,
                                               "residual": 0.5}}}
        route.fulfill(status=200, content_type="application/json", body=json.dumps(state))

    with Server(truth.path) as url:
        page = browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.route("**/api/frame/5", unsure)
        page.goto(url + "?frame=4")
        page.wait_for_selector("body[data-ready='1']")
        for i, x in enumerate((20.0, 30.0)):
            page.mouse.click(*page_xy(page, "cam0", (x, 25.0)))
            wait_version(page, i + 1)

        def u_of_a():
            return [lab["u"] for lab in page.evaluate("s3kLabel.app.frame.labels")]

        page.keyboard.press("Control+z")
        wait_version(page, 3)
        page.keyboard.press("Control+z")
        wait_version(page, 4)
        assert u_of_a() == []
        page.keyboard.press("Control+Shift+Z")  # redo, not undo
        wait_version(page, 5)
        assert u_of_a() == pytest.approx([20.0], abs=0.3)
        page.keyboard.press("Control+y")
        wait_version(page, 6)
        assert u_of_a() == pytest.approx([30.0], abs=0.3)
        page.keyboard.press("Control+y")  # nothing left to redo
        page.wait_for_function("document.getElementById('status').className === 'error'")
        assert "no undone edit to redo" in page.inner_text("#status")
        page.keyboard.press("Control+z")
        wait_version(page, 7)
        page.mouse.click(*page_xy(page, "cam0", (40.0, 25.0)))  # a new edit: nothing to redo any more
        wait_version(page, 8)
        page.keyboard.press("Control+Shift+Z")
        page.wait_for_function("document.getElementById('status').className === 'error'")
        assert u_of_a() == pytest.approx([40.0], abs=0.3)

        # accept with no confident view: said, nothing saved
        page.keyboard.press("ArrowRight")
        page.wait_for_function("document.body.dataset.frame === '5'")
        page.keyboard.press("a")
        page.wait_for_function("document.getElementById('status').className === 'note'")
        assert "nothing accepted" in page.inner_text("#status") and "below 0.5" in page.inner_text("#status")
        page.evaluate("setStatus('', '')")
        page.keyboard.press("Shift+A")  # accept all
        page.wait_for_function("document.getElementById('status').className === 'note'")
        status = page.inner_text("#status")
        assert "nothing accepted" in status and "any keypoint" in status
        assert page.evaluate("document.body.dataset.version") == "0"

        # a test frame, unlocked and left, is locked again; and it can be locked by hand
        page.keyboard.press("ArrowRight")
        page.wait_for_function("document.body.dataset.frame === '6'")
        assert page.evaluate("document.body.dataset.locked") == "1"
        page.click("#unlock")
        assert page.evaluate("document.body.dataset.locked") == "0" and page.inner_text("#unlock") == \
            "lock test frame"
        page.keyboard.press("ArrowLeft")
        page.wait_for_function("document.body.dataset.frame === '5'")
        page.keyboard.press("ArrowRight")
        page.wait_for_function("document.body.dataset.frame === '6'")
        assert page.evaluate("document.body.dataset.locked") == "1"
        page.mouse.click(*page_xy(page, "cam0", (20.0, 30.0)))
        page.wait_for_function("document.getElementById('status').className === 'error'")
        assert "read-only" in page.inner_text("#status")
        page.click("#unlock")
        page.click("#unlock")  # locked again by hand
        assert page.evaluate("document.body.dataset.locked") == "1"
        page.mouse.click(*page_xy(page, "cam0", (20.0, 30.0)))
        page.wait_for_function("document.getElementById('status').textContent.includes('read-only')")
        assert errors == []
    _, mask = Dataset.open(truth.path).labels([5, 6])
    assert not mask.any()


def test_the_ranking_n_goes_to_the_worst_frame_not_yet_seen_and_the_list_follows(tmp_path, browser):
    """``n`` takes the highest-ranked frame not yet opened; the list highlights the current frame's entry and
    scrolls to it; entry numbers of three digits are shown whole. The ranking is the server's format, made
    up here: 120 entries, the dataset's frames among made-up ones."""
    import json

    truth = make_label_dataset(tmp_path / "ds", size=64)
    order = [1000 + i for i in range(120)]
    order[0], order[1], order[2], order[116] = 3, 1, 2, 5
    rows = [{"frame": f, "score": 10.0 - i / 20, "residual_px": 1.0, "worst_view_px": 2.0, "confidence": 0.5}
            for i, f in enumerate(order)]

    def with_run(route):
        meta = route.fetch().json()
        meta["run"] = True
        route.fulfill(status=200, content_type="application/json", body=json.dumps(meta))

    with Server(truth.path) as url:
        page = browser.new_page(viewport={"width": 1500, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.route("**/api/meta", with_run)
        page.route("**/api/ranking*", lambda route: route.fulfill(status=200, content_type="application/json",
                                                                   body=json.dumps(rows)))
        page.goto(url)
        page.wait_for_selector("#ranking li")
        page.keyboard.press("n")
        page.wait_for_function("document.body.dataset.frame === '3'")
        page.locator("#ranking li[data-frame='2']").click()  # the third entry, opened by hand
        page.wait_for_function("document.body.dataset.frame === '2'")
        page.keyboard.press("n")  # the worst not yet seen: 1 (3 and 2 were)
        page.wait_for_function("document.body.dataset.frame === '1'")
        assert page.locator("#ranking li.current").get_attribute("data-frame") == "1"
        page.evaluate("s3kLabel.gotoFrame(5)")  # entry 117, far down the list: scrolled into sight
        page.wait_for_function("document.body.dataset.frame === '5'")
        current = page.locator("#ranking li.current")
        assert current.get_attribute("data-frame") == "5" and current.inner_text().startswith("117.")
        box, item = page.locator("#ranking").bounding_box(), current.bounding_box()
        assert box["y"] <= item["y"] and item["y"] + item["height"] <= box["y"] + box["height"] + 1
        ranks = page.eval_on_selector_all("#ranking .rank", "rs => rs.map(r => [r.textContent, "
                                          "r.getBoundingClientRect().left, r.scrollWidth <= r.clientWidth])")
        assert [r[0] for r in ranks] == [f"{i + 1}." for i in range(120)]
        assert all(left >= box["x"] and whole for _, left, whole in ranks)

        # 15 keypoint colours, each pair far apart in CIELAB (the hue circle gave greens 13 apart)
        hexes = page.evaluate("Array.from({length: 15}, (_, k) => s3kLabel.colour(k, 15))")
        assert errors == []
    rgb = np.array([[int(h[i:i + 2], 16) / 255 for i in (1, 3, 5)] for h in hexes])
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    xyz = lin @ np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]).T
    f = np.cbrt(np.maximum(xyz / [0.95047, 1.0, 1.08883], 0.008856))
    lab = np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], axis=1)
    gaps = np.linalg.norm(lab[:, None] - lab[None], axis=-1)[np.triu_indices(15, 1)]
    assert len(set(hexes)) == 15 and gaps.min() > 25


def test_the_queued_frames_lead_the_list_and_n_walks_them_in_rank_order(tmp_path, browser):
    """The frames s3k add-frames queued are the list (no run here), rank 1 first with the tracker's doubt;
    ``n`` opens it; once labelled it leaves the list and ``n`` opens the next queued frame."""
    from s3k.label.queue import queue_frames

    truth = make_label_dataset(tmp_path / "ds", size=64)
    queue_frames(truth.path, [(0, 9.0), (4, 7.5), (2, 3.25), (5, 1.0)], worst=3)  # 0 is labelled: passed over
    uv = truth.uv(4)
    with Server(truth.path) as url:
        page, errors = open_app(browser, url, 1500, 900)
        page.wait_for_selector("#ranking li")
        items = page.locator("#ranking li")
        assert [items.nth(i).get_attribute("data-frame") for i in range(items.count())] == ["4", "2", "5"]
        assert items.first.inner_text().replace("\n", " ") == "1. frame 4: 7.50 queued"
        assert not page.locator("#rank-by-label").is_visible()  # no run: the queue alone, no other order
        assert page.evaluate("document.body.dataset.frame") == "0"
        page.keyboard.press("n")
        page.wait_for_function("document.body.dataset.frame === '4'")
        assert page.locator("#ranking li.current").get_attribute("data-frame") == "4"
        page.mouse.click(*page_xy(page, "cam0", uv[0, 0]))  # labelled: frame 4 leaves the queue
        wait_version(page, 1)
        page.wait_for_function("[...document.querySelectorAll('#ranking li')].map((li) => li.dataset.frame)"
                               ".join() === '2,5'")
        page.keyboard.press("n")
        page.wait_for_function("document.body.dataset.frame === '2'")
        assert errors == []


def test_the_propagate_form_previews_copies_and_undoes_in_the_pages_words(tmp_path, browser):
    from s3k.label.store import Edit

    truth = make_label_dataset(tmp_path / "ds", size=64)
    uv = truth.uv(0)
    LabelStore.open(truth.path).save(0, [Edit(CAMERAS[c], kp, float(uv[c, k, 0]), float(uv[c, k, 1]))
                                         for k, kp in enumerate(["a", "b", "c"]) for c in (0, 1)], None)
    LabelStore.open(truth.path).save(2, [Edit("cam2", "a", 5.0, 5.0)], None)  # a label the copy would replace
    labels = (truth.path / "labels.csv").read_text()
    with Server(truth.path) as url:
        page = browser.new_page(viewport={"width": 1500, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "?frame=0")
        page.wait_for_selector("body[data-ready='1']")
        page.click("#propagate-box summary")
        page.fill("#prop-first", "0")
        page.fill("#prop-last", "3")
        page.click("#prop-copy")  # would replace frame 2's label: refused in the page's words
        page.wait_for_function("document.getElementById('status').className === 'error'")
        refusal = page.inner_text("#status")
        assert "would replace 1 existing label" in refusal and "'replace existing labels'" in refusal
        assert "--" not in refusal
        page.check("#prop-overwrite")
        page.click("#prop-preview")
        page.wait_for_function("document.getElementById('status').className === 'note'")
        assert "nothing was written" in page.inner_text("#status")
        assert "frame 2: 11 new label(s), 1 replaced" in page.inner_text("#prop-result")
        assert (truth.path / "labels.csv").read_text() == labels
        page.click("#prop-copy")
        page.wait_for_function("document.getElementById('status').textContent.startsWith('copied')")
        assert Dataset.open(truth.path).labels([1, 2, 3])[1].sum() == 3 * 12
        page.click("#prop-undo")
        page.wait_for_function("document.getElementById('status').textContent.startsWith('undid')")
        assert errors == []
    _, mask = Dataset.open(truth.path).labels([1, 2, 3])
    assert mask.sum() == 1 and mask[1, 2, 0]  # frame 2's own label back, frames 1 and 3 empty again


def residual_of(page, camera: str) -> tuple[str, str, str]:
    """The residual in a view's bar: its text, its level (the class) and the colour it is drawn in."""
    bar = page.locator(f".view[data-camera={camera}] .residual")
    colour = bar.evaluate("e => getComputedStyle(e).color")
    return bar.inner_text(), bar.get_attribute("data-level") or "", colour


def test_a_label_that_disagrees_turns_its_residual_red_and_lists_its_frame(tmp_path, browser):
    """One label 45 px from where the other three views put it (frame 5, keypoint b, cam2) and a careless one
    8 px off (frame 4, keypoint a, cam1): the first frame is listed under *Labels that disagree*, a click on
    it opens the frame at that keypoint with the view's residual red; the careless one is amber, the true
    ones green; put right, the frame leaves the list."""
    truth = make_label_dataset(tmp_path / "ds", size=96)
    label_true_projections(truth, {(5, 2, 1): FAR_PX, (4, 1, 0): NEAR_PX})
    red, amber, green = "rgb(255, 107, 107)", "rgb(240, 176, 64)", "rgb(159, 211, 160)"
    with Server(truth.path) as url:
        page, errors = open_app(browser, url, 1500, 900)
        page.wait_for_function("document.body.dataset.disagreements === '1'")
        entry = page.locator("#disagreements li")
        assert entry.count() == 1 and entry.get_attribute("data-frame") == "5"
        assert entry.inner_text().startswith("frame 5: b in cam2, 45.0 px")
        assert page.locator("#disagree-empty").is_hidden()
        assert "more than 40" in page.inner_text("#disagree-rule")
        assert page.evaluate("document.body.dataset.frame") == "0"
        for cam in CAMERAS:
            assert residual_of(page, cam)[1:] == ("ok", green)

        entry.click()
        page.wait_for_function("document.body.dataset.frame === '5'")
        page.wait_for_function("document.querySelector('#keypoints li.current').dataset.keypoint === 'b'")
        text, level, colour = residual_of(page, "cam2")
        assert (level, colour) == ("disagrees", red) and text.endswith("45.0 px from the others")
        assert page.locator("#disagreements li.current").count() == 1
        for cam in ("cam0", "cam1", "cam3"):
            assert residual_of(page, cam)[1] != "disagrees"

        page.evaluate("s3kLabel.gotoFrame(4)")
        page.wait_for_function("document.body.dataset.frame === '4'")
        page.locator("#keypoints li[data-keypoint=a]").click()
        assert residual_of(page, "cam1")[1:] == ("high", amber)

        # put right by a click at the true place: the list empties and the residual turns green
        page.locator("#disagreements li").click()
        page.wait_for_function("document.body.dataset.frame === '5'")
        page.wait_for_function("document.querySelector('#keypoints li.current').dataset.keypoint === 'b'")
        page.mouse.click(*page_xy(page, "cam2", truth.uv(5)[2, 1]))
        wait_version(page, 2)
        page.wait_for_function("document.body.dataset.disagreements === '0'")
        assert page.locator("#disagreements li").count() == 0 and page.locator("#disagree-empty").is_visible()
        assert residual_of(page, "cam2")[1:] == ("ok", green)
        assert errors == []
