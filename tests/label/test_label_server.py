"""``s3k label`` as a real server process: a SIGKILL while clicks arrive loses no acknowledged click, and
bound to another interface than the loopback it refuses requests without the printed token."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers.label_data import make_label_dataset
from helpers.paths import REPO as ROOT
from helpers.synthetic_rig import CAMERAS, KEYPOINTS

httpx = pytest.importorskip("httpx")
pytest.importorskip("uvicorn")

from s3k.data import Dataset  # noqa: E402
from s3k.label.store import HISTORY_FILE, LabelStore  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(data: Path, *extra: str) -> tuple[subprocess.Popen, str]:
    """Start ``s3k label DATA`` in its own process; returns it and the URL it printed."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "s3k.cli", "label", str(data), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    match = re.search(r"at (http://\S+)", line)
    assert match, line
    url = match.group(1)
    base = url.split("?")[0]
    host = re.match(r"http://([^/]+)/", base).group(1)
    probe = base.replace(host, f"127.0.0.1:{host.rsplit(':', 1)[1]}")
    for _ in range(300):  # until uvicorn listens
        try:
            httpx.get(probe + "static/app.css", timeout=1.0)
            break
        except httpx.TransportError:
            assert proc.poll() is None, proc.stdout.read()
            time.sleep(0.05)
    return proc, url


def test_sigkill_loses_no_acknowledged_click(tmp_path):
    truth = make_label_dataset(tmp_path / "ds", size=64)
    port = free_port()
    proc, url = start(truth.path, "--port", str(port), "--labeller", "kim")
    acked: list[tuple[int, str, str, float, float]] = []
    stop = threading.Event()
    rng = np.random.default_rng(0)

    def clicker():
        versions = {f: 0 for f in range(7)}
        with httpx.Client(base_url=url, timeout=5.0) as client:
            while not stop.is_set():
                f, c, k = int(rng.integers(7)), CAMERAS[rng.integers(4)], KEYPOINTS[rng.integers(3)]
                u, v = (float(x) for x in rng.uniform(0, 63, 2).round(3))
                try:
                    r = client.post(f"api/frame/{f}/label", json={"version": versions[f], "edits": [
                        {"camera": c, "keypoint": k, "u": u, "v": v}], "unlock": True})  # 6 is a test frame
                except httpx.TransportError:
                    return  # the server is gone: this click was never acknowledged
                assert r.status_code == 200, r.text
                versions[f] = r.json()["version"]
                acked.append((f, c, k, u, v))

    thread = threading.Thread(target=clicker)
    try:
        thread.start()
        deadline = time.monotonic() + 60
        while len(acked) < 15 and time.monotonic() < deadline and thread.is_alive():
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)  # while the clicker is still sending
        proc.wait(timeout=10)
    finally:
        stop.set()
        thread.join(timeout=10)
        if proc.poll() is None:
            proc.kill()
    assert len(acked) >= 15
    # the last acknowledged value of every (frame, camera, keypoint) is on disk, in labels.csv and the log
    last = {(f, c, k): (u, v) for f, c, k, u, v in acked}
    ds = Dataset.open(truth.path)
    for (f, c, k), (u, v) in last.items():
        uv, mask = ds.labels([f])
        ci, ki = CAMERAS.index(c), KEYPOINTS.index(k)
        assert mask[0, ci, ki]
        np.testing.assert_allclose(uv[0, ci, ki], (u, v), atol=1e-4)
    store = LabelStore.open(truth.path)
    logged = [(e["frame"], ch["camera"], ch["keypoint"], ch["after"]["u"], ch["after"]["v"])
              for e in store.history() for ch in e["changes"]]
    assert logged[: len(acked)] == acked
    assert all(e["labeller"] == "kim" for e in store.history())
    # a new server goes on from there: its versions are the log's
    proc, url = start(truth.path, "--port", str(free_port()))
    try:
        f = acked[-1][0]
        state = httpx.get(url + f"api/frame/{f}").json()
        assert state["version"] == sum(1 for e in store.history() if e["frame"] == f)
    finally:
        proc.kill()
        proc.wait(timeout=10)


def test_off_loopback_requests_need_the_printed_token(tmp_path):
    truth = make_label_dataset(tmp_path / "ds", size=32)
    port = free_port()
    proc, url = start(truth.path, "--host", "0.0.0.0", "--port", str(port))
    try:
        token = re.search(r"\?token=([\w-]+)", url)
        assert token, url
        base = f"http://127.0.0.1:{port}/"
        assert httpx.get(base + "api/meta").status_code == 403
        assert httpx.get(base + "api/frame/0/image/cam0").status_code == 403
        assert httpx.post(base + "api/frame/0/label", json={"version": 0, "edits": []}).status_code == 403
        assert httpx.get(base + "api/meta?token=" + token.group(1)[::-1]).status_code == 403
        with httpx.Client() as browser:
            page = browser.get(base + "?token=" + token.group(1))
            assert page.status_code == 200 and "s3k label" in page.text
            assert browser.get(base + "api/meta").status_code == 200  # its cookie carries the token
        assert not (truth.path / "labels.csv").exists() and not (truth.path / HISTORY_FILE).exists()
    finally:
        proc.kill()
        proc.wait(timeout=10)
