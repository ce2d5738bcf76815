"""``phantom-calib view``: a real-time browser view of the calibrated phantom.

Reads a work folder and a surrogate (never writes either; see :mod:`calib.viewer.scene`),
serves one offline page on 127.0.0.1 (:mod:`calib.viewer.server`, the design choice and
its reasons) and drives a headless Chromium for tests and screenshots
(:mod:`calib.viewer.headless`)::

    scene = load_scene("WORK", "MODEL.pt")
    server = make_server(scene, port=8050)   # PortInUseError names a free port
    server.serve_forever()
"""

from __future__ import annotations

from .scene import Frame, Predictor, Scene, SurfaceModelMismatchError, load_scene
from .server import PortInUseError, ViewerServer, find_free_port, make_server

__all__ = [
    "Frame",
    "PortInUseError",
    "Predictor",
    "Scene",
    "SurfaceModelMismatchError",
    "ViewerServer",
    "find_free_port",
    "load_scene",
    "make_server",
]
