"""The labelling server takes state-changing requests only from its own page (or a script), never from another
web page: every POST/PUT/PATCH/DELETE route, enumerated from the app so that a route added later is covered,
refuses a foreign ``Origin``, a cross-site ``Sec-Fetch-Site`` and any body that is not ``application/json``,
and changes nothing on disk when it refuses. (``tests/label/test_label_browser.py`` makes the same attempts
from a real page of another origin in Chromium.)"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from helpers.label_data import make_label_dataset
from helpers.synthetic_rig import CAMERAS, KEYPOINTS

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


PUBLIC = "https://labels.example.org"


def test_behind_a_reverse_proxy_the_public_pages_edits_are_taken_and_other_pages_still_refused(tmp_path):
    """With ``--public-url`` the page a TLS proxy serves (its origin, its Host forwarded) may edit the labels;
    without it the same request is refused, and pages of other origins are refused either way."""
    truth = make_label_dataset(tmp_path / "ds")
    path, body = f"/api/frame/{FRAME}/label", lambda c: BODIES[f"/api/frame/{FRAME}/label"](c)
    proxied = {"Origin": PUBLIC, "Host": "labels.example.org", "Content-Type": JSON}

    plain = TestClient(create_app(truth.path, allowed_hosts=["127.0.0.1", "localhost", "::1"]), base_url=OWN)
    assert plain.post(path, json=body(plain), headers={"Origin": PUBLIC}).status_code == 403
    assert plain.post(path, json=body(plain), headers=proxied).status_code == 400  # its Host is not allowed

    app = create_app(truth.path, allowed_hosts=["127.0.0.1", "localhost", "::1"], public_url=PUBLIC + "/")
    client = TestClient(app, base_url=OWN)
    root = client.app.state.label.root
    for origin in ("https://evil.example.org", "https://labels.example.org.evil.net", "https://labels.example.org:8443"):
        before = snapshot(root)
        r = client.post(path, json=body(client), headers={**proxied, "Origin": origin})
        assert r.status_code == 403, (origin, r.text)
        assert snapshot(root) == before
    assert client.post(path, json=body(client), headers={"Host": "evil.example.org"}).status_code == 400
    before = snapshot(root)
    r = client.post(path, json=body(client), headers=proxied)
    assert r.status_code == 200, r.text
    assert snapshot(root) != before
    r = client.post(path, json=body(client), headers={"Origin": OWN})  # the direct page still works
    assert r.status_code == 200, r.text


def test_behind_an_https_proxy_the_token_cookie_is_secure(tmp_path):
    truth = make_label_dataset(tmp_path / "ds")
    for public, secure in ((PUBLIC, True), ("http://labels.lab:8080", False)):
        client = TestClient(create_app(truth.path, token="t0k", public_url=public), base_url=OWN)
        cookie = client.get("/?token=t0k").headers["set-cookie"].lower()
        assert ("; secure" in cookie) == secure, (public, cookie)
        assert "httponly" in cookie and "samesite=strict" in cookie


@pytest.mark.parametrize("url, origin", [
    ("https://Labels.Example.org", "https://labels.example.org"),
    ("http://labels.lab:8080/", "http://labels.lab:8080"),
    ("https://[::1]:9000", "https://[::1]:9000"),
    ("https://labels.example.org:443", "https://labels.example.org"),
    ("http://labels.lab:80/", "http://labels.lab"),
])
def test_public_url_is_reduced_to_its_origin(url, origin):
    from s3k.label.server import public_origin
    assert public_origin(url)[0] == origin


@pytest.mark.parametrize("url", ["labels.example.org", "ftp://labels.example.org", "https://",
                                 "https://labels.example.org/s3k", "https://labels.example.org/?a=1",
                                 "https://user@labels.example.org", "https://labels.example.org:99999",
                                 "http://[::1", "https://[::1]x"])
def test_a_public_url_the_app_cannot_be_served_at_is_refused_in_one_line(url):
    from s3k.base.errors import UserError
    from s3k.label.server import public_origin
    with pytest.raises(UserError, match="--public-url") as info:
        public_origin(url)
    assert "\n" not in str(info.value)


def test_serving_behind_a_proxy_always_needs_the_token_and_prints_the_public_url(tmp_path, monkeypatch):
    """On the loopback, alone, the app needs no token; with ``--public-url`` anyone who reaches the proxy
    reaches it, so a token guards it and the printed URL is the proxy's."""
    import uvicorn

    from s3k.label import server

    truth = make_label_dataset(tmp_path / "ds")
    apps, said = [], []
    monkeypatch.setattr(uvicorn.Server, "run", lambda self: apps.append(self.config.app))
    server.serve(truth.path, port=8797, announce=said.append)
    server.serve(truth.path, port=8797, announce=said.append, public_url=PUBLIC)
    assert "http://127.0.0.1:8797/ " in said[0]
    url = re.search(r"(https://\S+)", said[1]).group(1)
    assert url.startswith(PUBLIC + "/?token=")
    guarded = TestClient(apps[1], base_url=OWN)
    assert guarded.get("/api/frame/0").status_code == 403
    assert guarded.get("/api/frame/0", headers={"x-s3k-token": url.split("=", 1)[1]}).status_code == 200
    assert TestClient(apps[0], base_url=OWN).get("/api/frame/0").status_code == 200


def test_behind_an_https_proxy_its_plain_http_twin_is_another_page(tmp_path):
    """The proxy forwards its Host to the app, which hears plain http: the origin allowed for that Host is
    the public URL's (its scheme included), never one built from the request, so ``http://`` + the public
    host is refused."""
    truth = make_label_dataset(tmp_path / "ds")
    client = TestClient(create_app(truth.path, public_url=PUBLIC), base_url=OWN)
    root = client.app.state.label.root
    path = f"/api/frame/{FRAME}/label"
    before = snapshot(root)
    for twin in ("http://labels.example.org", "http://labels.example.org:80"):
        r = client.post(path, json=BODIES[path](client),
                        headers={"Origin": twin, "Host": "labels.example.org", "Content-Type": JSON})
        assert r.status_code == 403, (twin, r.text)
    assert snapshot(root) == before
    r = client.post(path, json=BODIES[path](client),
                    headers={"Origin": PUBLIC, "Host": "labels.example.org", "Content-Type": JSON})
    assert r.status_code == 200, r.text


@pytest.mark.parametrize("public", ["https://labels.example.org:443", "https://labels.example.org"])
@pytest.mark.parametrize("origin", ["https://labels.example.org", "https://labels.example.org:443"])
def test_a_default_port_names_the_same_origin_on_either_side(tmp_path, public, origin):
    """Browsers leave the scheme's default port out of ``Origin``; ``--public-url https://host:443`` is the
    same origin."""
    truth = make_label_dataset(tmp_path / "ds")
    client = TestClient(create_app(truth.path, public_url=public), base_url=OWN)
    path = f"/api/frame/{FRAME}/label"
    r = client.post(path, json=BODIES[path](client),
                    headers={"Origin": origin, "Host": "labels.example.org", "Content-Type": JSON})
    assert r.status_code == 200, r.text


def test_a_malformed_public_url_is_refused_in_one_line(tmp_path, capsys):
    from s3k import cli

    truth = make_label_dataset(tmp_path / "ds")
    capsys.readouterr()
    assert cli.main(["label", str(truth.path), "--public-url", "http://[::1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--public-url" in err and "http://[::1" in err, err
