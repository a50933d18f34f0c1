"""The labelling app's web server (``s3k label``): a FastAPI application over one dataset folder.

The browser shows the views and takes the clicks; every computation is here, with s3k's calibration and
geometry (:mod:`s3k.label.solve`), and every edit goes through the dataset's
:class:`~s3k.label.store.LabelStore` (saved on disk before the reply). The API, all JSON except the images:

- ``GET /api/meta``: keypoints, cameras, image size, frames with their splits and label counts.
- ``GET /api/frame/{frame}``: the frame's labels, its version, the geometry (3D points, reprojections,
  residuals, epipolar curves) and, with a run, the run's suggestions.
- ``GET /api/frame/{frame}/image/{camera}``: the stored image, PNG.
- ``POST /api/frame/{frame}/label``: ``{"version", "edits": [{"camera", "keypoint", "u", "v", "visible",
  "remove"}], "source", "unlock"}``; answers the new frame state, 409 with the newer state (``current``) when
  ``version`` is stale, 400 naming the field when an edit is invalid, 403 for a test frame (its labels are
  held out for evaluation) unless ``unlock`` is true.
- ``POST /api/frame/{frame}/undo``: ``{"version", "unlock"}``; reverts the frame's latest edit not yet undone
  (the history keeps both), 400 when there is none. ``POST /api/frame/{frame}/redo``: the same body; reverts
  the latest undo not yet redone, 400 when there is none (or the frame was edited since).
- ``GET /api/frame/{frame}/history``: the frame's edit log.
- ``GET /api/disagreements``: per camera the median residual of its labels over the frames with labels, and
  the frames with a label more than 40 px from where the other views put it (docs/tracks.md's check), worst
  first (:mod:`s3k.label.agreement`); a frame's state colours each residual by both
  (:func:`s3k.label.solve.agreement_level`).
- ``GET /api/ranking?split=unlabelled&limit=100&by=doubt``: the frames ``s3k add-frames`` queued that are
  still unlabelled first, by rank, with the tracker's doubt (:func:`s3k.label.queue.queue_ranking`); then,
  with a run, the split's other frames ordered by the run's doubt, worst first; ``by=coverage``: by how far
  the run places them from every labelled frame's pose; ``by=representative``: poses in proportion to how
  often they occur (:mod:`s3k.label.suggest`).
- ``POST /api/propagate``: ``{"first", "last", "source", "max_changed", "overwrite", "allow_test",
  "dry_run"}``, :func:`s3k.label.propagate.propagate_labels` (refusals in the page's words), with
  ``per_frame`` (``{frame: [new, replaced]}``); ``POST /api/propagate/undo`` undoes the latest.
- ``POST /api/skeleton``: ``{"add": [a, b]}`` or ``{"remove": [a, b]}``; the dataset's skeleton (edges between
  keypoints, drawn in every view) after the change, written to ``s3k.json`` (:mod:`s3k.label.skeleton`).

Every request that changes the dataset (any method but GET, HEAD and OPTIONS) must come from the app's own
page or from a script, never from another web page: an ``Origin`` (or, without one, a ``Sec-Fetch-Site``)
other than the server's own is refused (403), and so is a body that is not ``application/json`` (415), which a
form or a ``no-cors`` fetch of another page cannot send. Request bodies larger than :data:`MAX_BODY_BYTES`
are refused unread (413). Files are served only from the
package's ``static`` folder; images only by frame id and camera name, so no
request names a path. Bound to another interface than the loopback, every request must carry the token the
server printed (``?token=`` in the first URL, then a cookie).
"""

from __future__ import annotations

import hmac
import logging
import secrets
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import cv2
import numpy as np
import torch
from fastapi import Body, FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel

from s3k.base.choices import Device
from s3k.base.errors import UserError
from s3k.base.messages import say
from s3k.base.metrics import mm_per_unit
from s3k.data import Dataset
from s3k.detector import Detector
from s3k.inference.session import RigSession
from s3k.label.agreement import LabelAgreement
from s3k.label.propagate import APP_WORDS, DEFAULT_MAX_CHANGED, propagate_labels, undo_propagation
from s3k.label.queue import queue_ranking
from s3k.label.skeleton import edit_skeleton
from s3k.label.solve import frame_geometry, triangulate_labels
from s3k.label.store import Edit, LabelStore, StaleVersion
from s3k.label.suggest import UP, Suggestions, Up

log = logging.getLogger(__name__)

__all__ = ["LOOPBACK", "LabelApp", "create_app", "serve"]

STATIC = Path(__file__).parent / "static"
LOOPBACK = ("127.0.0.1", "localhost", "::1")
TOKEN_COOKIE = "s3k_token"
MAX_BODY_BYTES = 1 << 20
"""The largest request body taken (a frame's edits are a few kB); larger ones are refused unread."""


class SaveIn(BaseModel):
    version: int
    edits: list[Edit]  # the store's own dataclass, validated field by field
    source: str = "click"
    unlock: bool = False  # edit a test frame


class UndoIn(BaseModel):
    version: int
    unlock: bool = False


class SkeletonIn(BaseModel):
    add: list[str] | None = None  # [keypoint, keypoint]
    remove: list[str] | None = None


class PropagateIn(BaseModel):
    first: int
    last: int
    source: int | None = None
    max_changed: float | None = None
    overwrite: bool = False
    allow_test: bool = False
    dry_run: bool = False


class LabelApp:
    """The state behind the API: the dataset, its label store and the optional run's suggestions."""

    def __init__(self, data: str | Path, run: str | Path | None = None, labeller: str | None = None,
                 device: Device = "cpu", up: Up = UP, ignore_geometry: bool = False) -> None:
        self.root = Path(data)
        self.up = up  # the table's normal in world coordinates: the pose rankings ignore the turn about it
        self.dataset = Dataset.open(self.root)
        self.store = LabelStore.open(self.root, labeller=labeller)
        self._label_points: dict[int, tuple[bytes, np.ndarray]] = {}  # frame -> (its labels, their 3D points)
        self.agreement = LabelAgreement(self.dataset, self.store)  # the labels that disagree
        self.suggestions = None
        if run is not None:  # a run shown other parts of the frames than it learnt suggests nonsense
            session = RigSession.on_dataset(Detector.load(run, device), self.dataset, ignore_geometry,
                                            "--ignore-geometry", rig=False)
            self.suggestions = Suggestions(session, self.root)

    def frame_state(self, frame: int) -> dict[str, Any]:
        self.store.refresh()
        state = self.store.frame_labels(frame)
        uv, mask = self.store.arrays(frame)
        cams = self.dataset.calibration([frame], np.float64)[0]
        agreement = self.agreement()
        medians = {cam: v["median_px"] for cam, v in agreement["cameras"].items()}
        state["geometry"] = frame_geometry(cams, uv, mask, self.dataset.keypoints, self.dataset.cameras,
                                           self.dataset.source_image_size, medians)
        state["agreement"] = {k: v for k, v in agreement.items() if k != "frames"}
        if self.suggestions is not None:
            state["suggestions"] = self.suggestions.suggestion(frame, self.dataset.cameras)
        return state

    def labelled_poses(self, keypoints: list[str]) -> list[np.ndarray]:
        """The 3D keypoints ``(K, 3)`` (in ``keypoints``' order, NaN where not triangulated) of every frame
        whose current labels triangulate two or more of them."""
        self.store.refresh()
        s = self.store
        order = [self.dataset.keypoints.index(k) for k in keypoints]
        counts = (s.present & s.visible).sum(axis=(1, 2))
        poses = []
        for i, f in enumerate(s.frames.ids):
            if counts[i] < 4:  # two keypoints in two views at least
                continue
            uv, mask = s.arrays(int(f))
            key = uv.tobytes() + mask.tobytes()
            known = self._label_points.get(int(f))
            if known is None or known[0] != key:  # triangulated once per state of the frame's labels
                cams = self.dataset.calibration([int(f)], np.float64)[0]
                known = self._label_points[int(f)] = (key, triangulate_labels(cams, uv, mask)["X"])
            X = known[1][order]
            if np.isfinite(X).all(-1).sum() >= 2:
                poses.append(X)
        return poses

    def meta(self) -> dict[str, Any]:
        self.store.refresh()
        s = self.store
        counts = (s.present & s.visible).sum(axis=(1, 2))
        frames = [{"frame": int(f), "split": str(s.frames.splits[i]), "labels": int(counts[i])}
                  for i, f in enumerate(s.frames.ids)]
        ds = self.dataset
        return {"keypoints": ds.keypoints, "cameras": ds.cameras, "image_size": list(ds.source_image_size),
                "units": ds.units, "skeleton": ds.skeleton, "calibration":
                "static" if ds.static_calibration else "per_frame", "frames": frames,
                "run": self.suggestions is not None, "path": str(self.root)}


def _error(status: int, message: str, **extra: Any) -> JSONResponse:
    return JSONResponse({"detail": message, **extra}, status_code=status)


DEFAULT_PORTS = {"http": 80, "https": 443}


def _origin(url: str) -> str | None:
    """``scheme://host[:port]`` of a URL or an ``Origin``, in lower case and without the scheme's default port
    (a browser names ``https://host``, never ``https://host:443``); None when it is no http(s) origin."""
    try:
        parts = urlsplit(url.strip())
        port = parts.port
    except ValueError:  # a port out of range, an unclosed [IPv6 address
        return None
    scheme, host = parts.scheme.lower(), (parts.hostname or "").lower()
    if scheme not in DEFAULT_PORTS or not host:
        return None
    shown = f"[{host}]" if ":" in host else host
    if parts.netloc.lower() != (shown if port is None else f"{shown}:{port}"):
        return None  # more than a host and port: a user, or text after a [IPv6 address]
    return f"{scheme}://{shown}" + ("" if port in (None, DEFAULT_PORTS[scheme]) else f":{port}")


def public_origin(url: str) -> tuple[str, str]:
    """``(origin, host)`` of ``--public-url``: the address a reverse proxy serves the app at, e.g.
    ``https://labels.example.org`` (scheme http or https, a host, an optional port, no path: the app's pages
    name their files from the root)."""
    origin = _origin(url)
    if origin is None:
        raise UserError(f"--public-url {url!r}: expected http(s)://HOST[:PORT], e.g. https://labels.example.org")
    parts = urlsplit(url.strip())
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username or parts.password:
        raise UserError(f"--public-url {url!r}: the app must be served at the root of its host, with no "
                        "path, query or user", hint="give the proxy a host name (or port) of its own")
    return origin, str(parts.hostname).lower()


def _cross_site(request: Request, public: tuple[str, str] | None = None) -> JSONResponse | None:
    """Why a state-changing request is refused as possibly sent by another web page (None: it is not).

    A page elsewhere can make the browser send a form or a ``no-cors`` fetch to this server (the Host check
    passes: the browser names 127.0.0.1). Such a request names its page's origin in ``Origin`` (or, from
    some browsers, only ``Sec-Fetch-Site``), and it cannot carry ``Content-Type: application/json`` without
    the server's consent (a CORS preflight, which this server never grants). So a request is taken only when
    its origin is this server's own (same scheme, host and port), ``public``'s (the origin a reverse proxy
    serves the page at, ``--public-url``, :func:`public_origin`) or unnamed (a script, not a browser page),
    and its body is JSON. A request whose ``Host`` is the public host came through the proxy: its own origin
    is the public one alone (the proxy's plain-http twin of an https origin is another page's).
    """
    own = _origin(f"{request.url.scheme}://{request.headers.get('host', '')}")
    if public is not None and own is not None and urlsplit(own).hostname == public[1]:
        own = public[0]
    origin = request.headers.get("origin")
    if origin is not None:
        if _origin(origin) not in {own, None if public is None else public[0]} - {None}:
            return _error(403, f"cross-site request refused: origin {origin!r} is not this app's ({own}); "
                               "edit the labels from the page s3k label serves")
    else:
        site = request.headers.get("sec-fetch-site")
        if site is not None and site.strip().lower() not in ("same-origin", "none"):
            return _error(403, f"cross-site request refused: Sec-Fetch-Site is {site!r}; edit the labels "
                               "from the page s3k label serves")
    kind = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if kind != "application/json":
        return _error(415, f"Content-Type {kind or 'missing'!r} refused: every request that changes the "
                           "dataset must send application/json")
    return None




def create_app(data: str | Path, run: str | Path | None = None, token: str | None = None,
               labeller: str | None = None, device: Device = "cpu", allowed_hosts: list[str] | None = None,
               up: Up = UP, ignore_geometry: bool = False, public_url: str | None = None) -> FastAPI:
    """The labelling app for the dataset ``data``.

    Args:
        data: dataset folder.
        run: a trained run folder whose predictions are offered as suggestions, or None.
        token: when given, every request must carry it (``?token=`` or the cookie set by the first page).
        labeller: name written into the edit history.
        device: where the run's detector runs.
        allowed_hosts: ``Host`` header values accepted (None: any), so that a web page elsewhere cannot
            reach a loopback server through a name that resolves to 127.0.0.1.
        up: the table's normal in world coordinates; the pose rankings compare poses blind to the object's
            turn about it (None: not blind to it).
        ignore_geometry: accept a run trained on another part of the cameras' frames than the dataset's
            images show (:func:`s3k.detector.geometry_record.check_dataset`).
        public_url: the address a reverse proxy serves the app at (:func:`public_origin`): its origin is the
            page's own too, its host an allowed ``Host``, and the token cookie is ``Secure`` under https.
    """
    public = None if public_url is None else public_origin(public_url)
    if public is not None and allowed_hosts is not None:
        allowed_hosts = [*allowed_hosts, public[1]]
    state = LabelApp(data, run, labeller, device, up, ignore_geometry)
    app = FastAPI(title="s3k label", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.label = state

    _add_guard(app, allowed_hosts, token, public)
    _add_frame_routes(app, state)
    _add_tool_routes(app, state)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


def _add_guard(app: FastAPI, allowed_hosts: list[str] | None, token: str | None,
               public: tuple[str, str] | None = None) -> None:
    """Every request's checks: a capped body, an allowed ``Host``, the origin (its own or ``public``), the
    token."""

    @app.middleware("http")
    async def guard(request: Request, call_next):
        if request.method not in ("GET", "HEAD", "OPTIONS"):  # bodies are read whole: their size is capped
            length = request.headers.get("content-length", "")
            if not length.isdigit():
                return _error(411, "a request body needs a Content-Length")
            if int(length) > MAX_BODY_BYTES:
                return _error(413, f"request body of {length} bytes; at most {MAX_BODY_BYTES} are accepted")
        if allowed_hosts is not None:
            host = request.headers.get("host", "").rsplit(":", 1)[0].strip("[]")
            if host not in allowed_hosts:
                return _error(400, f"host {host!r} refused; open the URL s3k label printed")
        if request.method not in ("GET", "HEAD", "OPTIONS"):
            refused = _cross_site(request, public)
            if refused is not None:
                return refused
        given = None
        if token is not None:
            given = request.query_params.get("token") or request.cookies.get(TOKEN_COOKIE) \
                or request.headers.get("x-s3k-token")
            if given is None or not hmac.compare_digest(given, token):
                return _error(403, "missing or wrong token; open the URL s3k label printed (with ?token=...)")
        response = await call_next(request)
        if token is not None and request.query_params.get("token"):
            response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict",
                                secure=public is not None and public[0].startswith("https:"))
        return response


def _add_frame_routes(app: FastAPI, state: LabelApp) -> None:
    """The page, the dataset's meta, a frame's state, images, labels, undo and history."""

    def frame_or_404(frame: int) -> int:
        if frame not in state.store.frames.row_of:
            raise HTTPException(404, f"frame {frame} is not in {state.root / 'frames.csv'}")
        return frame

    @app.get("/")
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    @app.get("/api/meta")
    def meta() -> dict[str, Any]:
        return state.meta()

    @app.get("/api/frame/{frame}")
    def frame(frame: int) -> dict[str, Any]:
        return state.frame_state(frame_or_404(frame))

    @app.get("/api/frame/{frame}/image/{camera}")
    def image(frame: int, camera: str) -> Response:
        frame_or_404(frame)
        if camera not in state.dataset.cameras:
            raise HTTPException(404, f"unknown camera {camera!r}")
        rgb = state.dataset.images([frame])[0, state.dataset.cameras.index(camera)]
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise HTTPException(500, "could not encode the image")
        return Response(png.tobytes(), media_type="image/png", headers={"Cache-Control": "max-age=3600"})

    def locked(frame: int, unlock: bool) -> JSONResponse | None:
        state.store.refresh()
        if state.store.split(frame) == "test" and not unlock:
            return _error(403, f"frame {frame} is a test frame: its labels are held out for evaluation and "
                               "read-only until unlocked (the page's unlock button)")
        return None

    @app.post("/api/frame/{frame}/label")
    def save(frame: int, body: SaveIn) -> Any:
        frame_or_404(frame)
        refused = locked(frame, body.unlock)
        if refused is not None:
            return refused
        edits = list(body.edits)
        try:
            state.store.save(frame, edits, body.version, source=body.source[:40])
        except StaleVersion as exc:
            return _error(409, str(exc), current=state.frame_state(frame))
        except UserError as exc:
            return _error(400, str(exc))
        return state.frame_state(frame)

    @app.post("/api/frame/{frame}/undo")
    def undo(frame: int, body: UndoIn) -> Any:
        return step(frame, body, state.store.undo)

    @app.post("/api/frame/{frame}/redo")
    def redo(frame: int, body: UndoIn) -> Any:
        return step(frame, body, state.store.redo)

    def step(frame: int, body: UndoIn, how: Any) -> Any:
        frame_or_404(frame)
        refused = locked(frame, body.unlock)
        if refused is not None:
            return refused
        try:
            how(frame, body.version)
        except StaleVersion as exc:
            return _error(409, str(exc), current=state.frame_state(frame))
        except UserError as exc:
            return _error(400, str(exc))
        return state.frame_state(frame)

    @app.get("/api/frame/{frame}/history")
    def history(frame: int) -> list[dict[str, Any]]:
        return state.store.history(frame_or_404(frame))


def _add_tool_routes(app: FastAPI, state: LabelApp) -> None:
    """The run's rankings of frames, the labels that disagree, propagation of a frame's labels over still
    frames (with its undo), and the skeleton's edits."""

    @app.get("/api/ranking")
    def ranking(split: str = "unlabelled", limit: int = 100, by: str = "doubt") -> Any:
        if split not in ("labelled", "unlabelled", "test", "all"):
            return _error(400, f"unknown split {split!r}")
        if by not in ("doubt", "coverage", "representative"):
            return _error(400, f"by: unknown ranking {by!r} (doubt, coverage or representative)")
        state.store.refresh()
        try:  # the queue's frames still unlabelled first, then the run's ranking of the others
            queued, ids = queue_ranking(state.root, state.store.frames.ids, state.store.frames.splits, split,
                                        shown=state.dataset.frames())
        except UserError as exc:
            return _error(400, str(exc))
        limit = max(0, limit)
        if state.suggestions is None:
            if queued:
                return queued[:limit]
            return _error(404, "no run and no frames queued: start s3k label with --run RUN to rank frames")
        if by in ("coverage", "representative"):
            poses = state.labelled_poses(state.suggestions.keypoints)
            return (queued + state.suggestions.coverage(ids, poses, mm_per_unit(state.dataset.units), limit,
                                                        order=by, up=state.up))[:limit]
        return (queued + state.suggestions.ranking(ids))[:limit]

    @app.get("/api/disagreements")
    def disagreements() -> dict[str, Any]:
        return state.agreement()

    @app.post("/api/propagate")
    def propagate(body: PropagateIn = Body(...)) -> Any:  # noqa: B008 - FastAPI's way
        limit = DEFAULT_MAX_CHANGED if body.max_changed is None else body.max_changed
        try:
            result = propagate_labels(state.root, body.first, body.last, body.source, limit,
                                      store=state.store, overwrite=body.overwrite, allow_test=body.allow_test,
                                      dry_run=body.dry_run, words=APP_WORDS)
        except UserError as exc:
            return _error(400, str(exc))
        return {"source": result.source, "frames": result.frames, "keypoints": result.keypoints,
                "labels": result.labels, "replaced": result.replaced, "dry_run": result.dry_run,
                "per_frame": {str(f): list(n) for f, n in sorted(result.per_frame.items())}}

    @app.post("/api/propagate/undo")
    def propagate_undo() -> Any:
        try:
            source, frames = undo_propagation(state.root, store=state.store)
        except UserError as exc:
            return _error(400, str(exc))
        return {"source": source, "frames": frames}

    @app.post("/api/skeleton")
    def skeleton(body: SkeletonIn) -> Any:
        try:
            edges = edit_skeleton(state.root, state.dataset.keypoints, add=body.add, remove=body.remove)
        except UserError as exc:
            return _error(400, str(exc))
        state.dataset.skeleton = edges
        return {"skeleton": [list(e) for e in edges]}


def serve(data: str | Path, run: str | Path | None = None, host: str = "127.0.0.1", port: int = 8765,
          labeller: str | None = None, device: Device = "cpu", announce: Callable[[str], None] | None = None,
          up: Up = UP, ignore_geometry: bool = False, public_url: str | None = None) -> None:
    """Run the app with uvicorn until interrupted. Off the loopback, or behind a reverse proxy at
    ``public_url``, a random token guards it."""
    import uvicorn

    announce = announce or say
    public = None if public_url is None else public_origin(public_url)

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family) as probe:  # a port in use is the user's to change, said in one line
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise UserError(f"cannot serve on {host}:{port}: {exc.strerror}",
                            hint="pass another --port (or --host)") from None

    # a request's geometry is a handful of tiny tensors: one thread each is fastest and leaves the cores free
    torch.set_num_threads(1)
    loopback = host in LOOPBACK
    token = None if loopback and public is None else secrets.token_urlsafe(18)
    hosts = [*LOOPBACK, host] if loopback else None
    app = create_app(data, run, token, labeller, device, allowed_hosts=hosts, up=up,
                     ignore_geometry=ignore_geometry, public_url=public_url)
    shown = f"[{host}]" if ":" in host else host
    base = f"http://{shown}:{port}" if public is None else public[0]
    url = f"{base}/" + ("" if token is None else f"?token={token}")
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False)
    server = uvicorn.Server(config)
    announce(f"s3k label: serving {data} at {url} (Ctrl-C to stop)")
    server.run()
