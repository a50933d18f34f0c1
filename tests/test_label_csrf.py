"""The labelling server takes state-changing requests only from its own page (or a script), never from another
web page: every POST/PUT/PATCH/DELETE route, enumerated from the app so that a route added later is covered,
refuses a foreign ``Origin``, a cross-site ``Sec-Fetch-Site`` and any body that is not ``application/json``,
and changes nothing on disk when it refuses. (``tests/test_label_browser.py`` makes the same attempts from a
real page of another origin in Chromium.)"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from label_data import make_label_dataset
from synthetic_rig import CAMERAS, KEYPOINTS

pytest.importorskip("fastapi")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.routing import APIRoute
    from fastapi.testclient import TestClient

from s3k.label.server import create_app

OWN = "http://127.0.0.1:8795"
JSON = "application/json"
CHANGING = {"POST", "PUT", "PATCH", "DELETE"}
FRAME = 4  # the frame a route's {frame} names


def changing_routes(app) -> list[tuple[str, str]]:
    """``(method, path)`` of every route of the app that may change state, ``{...}`` filled in."""
    out = []
    for route in app.routes:
        if isinstance(route, APIRoute):
            for method in sorted(route.methods & CHANGING):
                out.append((method, re.sub(r"\{[^}]+\}", str(FRAME), route.path)))
    return out


def version(client: TestClient) -> int:
    return client.get(f"/api/frame/{FRAME}").json()["version"]


# a body each route accepts in the state `prepared` leaves (a route added without one here fails the test)
BODIES: dict[str, Callable[[TestClient], dict[str, Any]]] = {
    f"/api/frame/{FRAME}/label": lambda c: {"version": version(c), "edits": [
        {"camera": "cam0", "keypoint": "b", "u": 20.0, "v": 30.0}]},
    f"/api/frame/{FRAME}/undo": lambda c: {"version": version(c)},
    f"/api/frame/{FRAME}/redo": lambda c: {"version": version(c)},
    "/api/propagate": lambda c: {"first": 0, "last": 3, "overwrite": True},
    "/api/propagate/undo": lambda c: {},
    "/api/skeleton": lambda c: {"add": ["a", "c"]},
}


def prepared(path: Path) -> TestClient:
    """A dataset where every state-changing route has something to change: frame 0 labelled in two views and
    propagated over frames 1-2 (to undo; frame 3 left to propagate to), frame 4 edited twice and undone once
    (to undo and to redo)."""
    truth = make_label_dataset(path)
    client = TestClient(create_app(truth.path), base_url=OWN)
    uv = truth.uv(0)
    edits = [{"camera": CAMERAS[c], "keypoint": kp, "u": float(uv[c, k, 0]), "v": float(uv[c, k, 1])}
             for k, kp in enumerate(KEYPOINTS) for c in (0, 1)]
    assert client.post("/api/frame/0/label", json={"version": 0, "edits": edits}).status_code == 200
    assert client.post("/api/propagate", json={"first": 0, "last": 2}).status_code == 200
    for u in (10.0, 12.0):
        edit = {"camera": "cam1", "keypoint": "a", "u": u, "v": 11.0}
        assert client.post(f"/api/frame/{FRAME}/label", json={"version": version(client), "edits": [edit]}
                           ).status_code == 200
    assert client.post(f"/api/frame/{FRAME}/undo", json={"version": version(client)}).status_code == 200
    return client


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


REFUSED = [  # (headers, status)
    ({"Origin": "http://127.0.0.1:8796", "Content-Type": JSON}, 403),  # another port
    ({"Origin": "http://localhost:8795", "Content-Type": JSON}, 403),  # another host name
    ({"Origin": "https://127.0.0.1:8795", "Content-Type": JSON}, 403),  # another scheme
    ({"Origin": "null", "Content-Type": JSON}, 403),  # a sandboxed or file page
    ({"Origin": "http://127.0.0.1:8796", "Content-Type": "text/plain"}, 403),
    ({"Sec-Fetch-Site": "cross-site", "Content-Type": JSON}, 403),  # no Origin
    ({"Sec-Fetch-Site": "same-site", "Content-Type": JSON}, 403),
    ({"Origin": OWN, "Content-Type": "application/x-www-form-urlencoded"}, 415),  # what a form sends
    ({"Origin": OWN, "Content-Type": "multipart/form-data; boundary=x"}, 415),
    ({"Origin": OWN, "Content-Type": "text/plain;charset=UTF-8"}, 415),  # a no-cors fetch's string body
    ({"Content-Type": "text/plain"}, 415),
    ({}, 415),  # no content type at all
]


def test_every_state_changing_route_refuses_other_pages_and_non_json_bodies(tmp_path):
    client = prepared(tmp_path / "ds")
    root = client.app.state.label.root
    routes = changing_routes(client.app)
    assert {p for _, p in routes} >= {f"/api/frame/{FRAME}/label", "/api/propagate/undo"}
    before = snapshot(root)
    for method, path in routes:
        body = json.dumps(BODIES.get(path, lambda c: {})(client)).encode()
        for headers, status in REFUSED:
            r = client.request(method, path, content=body, headers=headers)
            assert r.status_code == status, (method, path, headers, r.text)
            assert "refused" in r.json()["detail"]
            assert snapshot(root) == before, (method, path, headers)
    missing = sorted({p for _, p in routes} - set(BODIES))
    assert not missing, f"state-changing route(s) {missing} need an accepted body in BODIES"


@pytest.mark.parametrize("headers", [{"Origin": OWN}, {"Origin": OWN.upper()},
                                     {"Sec-Fetch-Site": "same-origin"}, {"Sec-Fetch-Site": "none"}, {}],
                         ids=["own-origin", "own-origin-upper-case", "same-origin", "typed-url", "script"])
def test_the_apps_own_json_requests_are_taken(tmp_path, headers):
    client = prepared(tmp_path / "ds")
    root = client.app.state.label.root
    for method, path in changing_routes(client.app):  # in the app's order: label, undo, ..., propagate/undo
        before = snapshot(root)
        r = client.request(method, path, json=BODIES[path](client),
                           headers={**headers, "Content-Type": "application/json; charset=utf-8"})
        assert r.status_code == 200, (method, path, r.text)
        assert snapshot(root) != before, (method, path)  # it did change the dataset
