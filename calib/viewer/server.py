"""The local HTTP server of ``phantom-calib view`` (stdlib, 127.0.0.1 only).

Why this design: a threaded ``http.server`` on the loopback interface serves one static
page (``static/index.html`` + ``static/viewer.js``, a small hand-written WebGL2 renderer:
no CDN, no npm, works offline) and evaluates the surrogate in Python, where it already
runs (:meth:`nn.Surrogate.predict`, TorchScript, both surrogate kinds, with its input
checks). A control change costs one loopback ``fetch`` of a float32 array (a few ms: a
surrogate query is ~0.1 ms, the HTTP round trip ~1-3 ms), well inside the issue's 30 ms;
porting the surrogate to JavaScript/ONNX would duplicate its checks for no measurable
gain, and a websocket or a framework (trame, dash) would add dependencies.

Routes (GET): ``/`` the page; ``/static/<file>``; ``/api/scene`` (JSON: model, scans,
states, landmarks, what is missing); ``/api/surface`` (float32 rest positions + uint32
triangles); ``/api/predict?g=X,Y,Z&c1=C1`` (float32: the surface vertices, then nipple
and tumour, NaN where absent; header ``X-Extrapolating``); ``/api/state/<scan>``
(float32 vertices of a saved FE state, then its nipple and tumour);
``/api/overlay/<scan>`` (float32 vertices, uint32 triangles, the ``n_scored_faces``
whose error is measured first, float32 error maps; layout in the ``X-Layout`` header).
"""

from __future__ import annotations

import errno
import json
import socket
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlparse

import numpy as np

from .scene import Scene

__all__ = ["PortInUseError", "ViewerServer", "find_free_port", "make_server"]

HOST = "127.0.0.1"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8"}


class PortInUseError(OSError):
    """The requested port is taken; the message names a free one."""


def find_free_port(start: int, *, tries: int = 50) -> int:
    """The first port from ``start + 1`` on that binds on 127.0.0.1 (else an ephemeral one)."""
    for port in range(start + 1, min(start + 1 + tries, 65536)):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((HOST, port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def _f32(*arrays) -> bytes:
    return b"".join(np.ascontiguousarray(a, dtype="<f4").tobytes() for a in arrays)


def _nan3(v) -> np.ndarray:
    return np.full(3, np.nan) if v is None else np.asarray(v, float)


class _Handler(BaseHTTPRequestHandler):
    scene: Scene  # set by partial()
    protocol_version = "HTTP/1.1"  # keep-alive: one loopback connection for every frame
    # TCP_NODELAY: headers and body go out in two writes; with Nagle's algorithm the body
    # waits for the client's delayed ACK (40 ms on Linux) on a kept-alive connection
    disable_nagle_algorithm = True

    def __init__(self, *args, scene: Scene, **kw):
        self.scene = scene
        super().__init__(*args, **kw)

    def log_message(self, format, *args):  # the stdlib's name
        pass  # quiet: one line per frame would flood the terminal

    def _send(self, body: bytes, ctype: str, status: int = 200, headers: dict | None = None):
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _error(self, status: int, message: str):
        self._send(json.dumps({"error": message}).encode(), "application/json", status)

    def do_GET(self):  # the stdlib's name
        url = urlparse(self.path)
        path = unquote(url.path)
        try:
            if path in ("/", "/index.html"):
                return self._static("index.html")
            if path.startswith("/static/"):
                return self._static(path[len("/static/") :])
            if path == "/api/scene":
                doc = dict(self.scene.info, missing=self.scene.missing)
                doc["has_surface"] = self.scene.rest_mm is not None
                return self._send(json.dumps(doc).encode(), "application/json")
            if path == "/api/surface":
                return self._surface()
            if path == "/api/predict":
                return self._predict(parse_qs(url.query))
            if path.startswith("/api/state/"):
                return self._state(path[len("/api/state/") :])
            if path.startswith("/api/overlay/"):
                return self._overlay(path[len("/api/overlay/") :])
        except ValueError as exc:
            return self._error(400, str(exc))
        return self._error(404, f"no such resource: {path}")

    def _static(self, name: str):
        if "/" in name or name.startswith("."):
            return self._error(404, f"no such file: {name}")
        res = resources.files("calib.viewer").joinpath("static", name)
        if not res.is_file():
            return self._error(404, f"no such file: {name}")
        ctype = _TYPES.get(Path(name).suffix, "application/octet-stream")
        return self._send(res.read_bytes(), ctype)

    def _surface(self):
        s = self.scene
        if s.rest_mm is None:
            return self._error(404, "no model surface: " + "; ".join(s.missing))
        body = _f32(s.rest_mm) + np.ascontiguousarray(s.faces, dtype="<u4").tobytes()
        layout = {"n_vertices": len(s.rest_mm), "n_faces": len(s.faces)}
        return self._send(
            body, "application/octet-stream", headers={"X-Layout": json.dumps(layout)}
        )

    def _predict(self, query: dict):
        p = self.scene.predictor
        if p is None:
            return self._error(404, "no surrogate: start the view with --model MODEL.pt")
        try:
            g = [float(v) for v in query["g"][0].split(",")]
            c1 = float(query["c1"][0])
        except (KeyError, ValueError, IndexError) as exc:
            raise ValueError(f"/api/predict needs g=X,Y,Z and c1=C1 ({exc})") from exc
        if len(g) != 3:
            raise ValueError(f"g must be X,Y,Z, got {query['g'][0]!r}")
        fr = p.predict(g, c1)
        body = _f32(fr.surface_mm, _nan3(fr.nipple_mm), _nan3(fr.tumour_mm))
        hdr = {"X-Extrapolating": "1" if fr.extrapolating else "0"}
        return self._send(body, "application/octet-stream", headers=hdr)

    def _state(self, name: str):
        st = self.scene.states.get(name)
        if st is None:
            return self._error(
                404, f"no saved FE state {name!r}; states: {sorted(self.scene.states)}"
            )
        pos, nipple, tumour = st
        return self._send(_f32(pos, _nan3(nipple), _nan3(tumour)), "application/octet-stream")

    def _overlay(self, name: str):
        ov = self.scene.overlays.get(name)
        if ov is None:
            return self._error(404, f"no scan {name!r}; scans: {sorted(self.scene.overlays)}")
        maps = [k for k in ("error_mm", "error_after_mm") if k in ov]
        body = (
            _f32(ov["vertices_mm"])
            + np.ascontiguousarray(ov["faces"], dtype="<u4").tobytes()
            + _f32(*(ov[k] for k in maps))
        )
        layout = {
            "n_vertices": len(ov["vertices_mm"]),
            "n_faces": len(ov["faces"]),
            "n_scored_faces": ov["n_scored_faces"],
            "maps": maps,
        }
        return self._send(
            body, "application/octet-stream", headers={"X-Layout": json.dumps(layout)}
        )


class ViewerServer(ThreadingHTTPServer):
    """A threaded HTTP server of one :class:`Scene` on 127.0.0.1."""

    daemon_threads = True
    allow_reuse_address = True  # SO_REUSEADDR: rebinding over TIME_WAIT; a listener still fails

    @property
    def url(self) -> str:
        """``http://127.0.0.1:PORT/``."""
        return f"http://{HOST}:{self.server_address[1]}/"


def make_server(scene: Scene, *, port: int = 8050) -> ViewerServer:
    """Bind the view's server (call ``serve_forever`` on it, or run it in a thread).

    Parameters
    ----------
    scene : Scene
    port : int
        TCP port on 127.0.0.1 (0: any free port).

    Raises
    ------
    PortInUseError
        The port is taken; the message suggests a free one.
    """
    try:
        return ViewerServer((HOST, port), partial(_Handler, scene=scene))
    except OSError as exc:
        if exc.errno in (errno.EADDRINUSE, errno.EACCES):
            free = find_free_port(port)
            raise PortInUseError(
                f"port {port} on {HOST} is in use (or not allowed); "
                f"port {free} is free: try --port {free}",
            ) from exc
        raise
