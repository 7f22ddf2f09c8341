"""The viewer's HTTP server: Python's standard library (``ThreadingHTTPServer``), no dependency.

Routes:

- ``GET /``, ``GET /viewer.js``: the page (package data in ``static/``).
- ``GET /api/scene``: JSON: name, Gaussians, available modes, samplers, the legend of predicted
  classes, the initial camera (eye, target, up, fov_y: the scene's overview), frame size, the
  scene's radius and the views the page steps through (the overview, then the scene's cameras).
- ``GET /api/frame?eye=x,y,z&target=x,y,z&up=x,y,z&fov_y=D&width=W&height=H&mode=M&query=Q&sampler=S&k=K``:
  a JPEG of the frame, its render time in the ``X-Render-Ms`` header. A bad request or an
  unknown query: status 400 / 404 with JSON ``{"error": message}``.

Frames are CPU renders sent as images, so the page needs no WebGL (headless browsers without a
GPU show it) and the server needs nothing beyond the standard library and matplotlib (JPEG).
"""
from __future__ import annotations

import io
import json
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlparse

import numpy as np
from matplotlib.image import imsave

from ...runtime import DEFAULTS, SAMPLERS
from ..query.text import QueryError, UnknownQueryError
from .frames import FrameRenderer, FrameRequest
from .views import scene_radius, scene_views

#: Static files of the page: name -> content type.
STATIC = {"index.html": "text/html; charset=utf-8", "viewer.js": "text/javascript; charset=utf-8"}
#: JPEG quality of frames.
JPEG_QUALITY = 90


def encode_jpeg(image: np.ndarray) -> bytes:
    """JPEG bytes of an image [H,W,3] uint8."""
    buf = io.BytesIO()
    imsave(buf, image, format="jpeg", pil_kwargs={"quality": JPEG_QUALITY})
    return buf.getvalue()


def initial_view(renderer: FrameRenderer, width: int, height: int, up_axis: int = 2) -> dict:
    """The page's first camera, the overview of :func:`~.views.scene_views` (eye, target, up,
    fov_y), with the frame size, the scene's radius (:func:`~.views.scene_radius`) and "views":
    all the views the page steps through, the overview first, then the scene's cameras:
    {"eye", "target", "up", "fov_y", "width", "height", "radius", "views"}."""
    scene = renderer.scene
    views = scene_views(scene.gaussians, scene.cameras, width, height, up_axis)
    first = {key: views[0][key] for key in ("eye", "target", "up", "fov_y")}
    return {**first, "width": width, "height": height, "radius": scene_radius(scene.gaussians.means),
            "views": views}


def _vector(params: dict, name: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in params[name][0].split(","))
    except (KeyError, ValueError):
        raise QueryError(f"{name}: expected three comma-separated numbers") from None
    if len(values) != 3:
        raise QueryError(f"{name}: expected three comma-separated numbers")
    return values


def parse_frame_request(query: str) -> FrameRequest:
    """The :class:`FrameRequest` of a ``/api/frame`` query string; QueryError naming a missing or
    malformed field."""
    params = parse_qs(query)

    def one(name: str, kind, default=None):
        if name not in params:
            if default is None:
                raise QueryError(f"{name}: missing")
            return default
        try:
            return kind(params[name][0])
        except ValueError:
            raise QueryError(f"{name}={params[name][0]!r}: not a {kind.__name__}") from None
    request = FrameRequest(_vector(params, "eye"), _vector(params, "target"), _vector(params, "up"),
                           one("fov_y", float), one("width", int), one("height", int), one("mode", str, "rgb"),
                           one("query", str, ""), one("sampler", str, DEFAULTS.sampler), one("k", int, DEFAULTS.k))
    request.check()
    return request


class ViewerServer(ThreadingHTTPServer):
    """The viewer's server: ``renderer`` renders frames, ``view`` is :func:`initial_view`'s dict."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], renderer: FrameRenderer, view: dict, k: int = DEFAULTS.k,
                 sampler: str = DEFAULTS.sampler):
        self.renderer, self.view, self.k, self.sampler = renderer, view, k, sampler
        super().__init__(address, ViewerHandler)

    @property
    def url(self) -> str:
        """http://host:port/ of the page."""
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    def scene_info(self) -> dict:
        """The JSON of ``/api/scene``."""
        r = self.renderer
        return {"name": r.scene.name, "gaussians": len(r.scene.gaussians), "modes": r.modes(),
                "samplers": list(SAMPLERS), "sampler": self.sampler, "k": self.k, "score": r.method,
                "legend": r.legend, "camera": self.view}


class ViewerHandler(BaseHTTPRequestHandler):
    """Serves the routes of the module docstring."""

    server: ViewerServer

    def do_GET(self) -> None:  # noqa: N802 (the standard library's name)
        url = urlparse(self.path)
        name = url.path.lstrip("/") or "index.html"
        if name in STATIC:
            self._send(200, STATIC[name], (resources.files(__package__) / "static" / name).read_bytes())
        elif name == "api/scene":
            self._send(200, "application/json", json.dumps(self.server.scene_info()).encode())
        elif name == "api/frame":
            self._frame(url.query)
        else:
            self._error(404, f"no such page: {url.path}")

    def _frame(self, query: str) -> None:
        try:
            image, ms = self.server.renderer.render(parse_frame_request(query))
        except UnknownQueryError as exc:
            return self._error(404, str(exc))
        except QueryError as exc:
            return self._error(400, str(exc))
        self._send(200, "image/jpeg", encode_jpeg(image),
                   {"X-Render-Ms": f"{ms:.1f}", "Access-Control-Expose-Headers": "X-Render-Ms"})

    def _error(self, status: int, message: str) -> None:
        self._send(status, "application/json", json.dumps({"error": message}).encode())

    def _send(self, status: int, kind: str, body: bytes, headers: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (the standard library's name)
        """Quiet: a frame a few times a second would flood the terminal."""
