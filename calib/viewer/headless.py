"""A headless Chromium driven over the DevTools protocol (tests, benchmark, screenshots).

Starts the system ``chromium`` (Debian's package) with ``--headless`` and a
``--remote-debugging-port=0`` whose port it reads from ``DevToolsActivePort`` in its own
profile folder, opens one page and talks to it over the page's websocket with
``websocket-client`` (``Runtime.evaluate``, ``Page.captureScreenshot``; protocol:
https://chromedevtools.github.io/devtools-protocol/). WebGL runs on SwiftShader (CPU).
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

from ..io import atomic_write

__all__ = ["BrowserError", "HeadlessBrowser", "find_chromium"]


class BrowserError(RuntimeError):
    """Chromium is missing, did not start, or a page script failed."""


def find_chromium() -> str | None:
    """Path of a Chromium executable (``$CHROMIUM``, then ``chromium`` on PATH), or None."""
    env = os.environ.get("CHROMIUM")
    if env:
        return env
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


class HeadlessBrowser:
    """One headless Chromium page (a context manager).

    Parameters
    ----------
    width, height : int
        Window size in CSS pixels.
    executable : str, optional
        Chromium to run (default :func:`find_chromium`).
    timeout_s : float
        Start-up and per-call timeout.
    """

    def __init__(self, *, width=1100, height=700, executable=None, timeout_s=30.0):
        self.executable = executable or find_chromium()
        if self.executable is None:
            raise BrowserError("no chromium found (apt-get install chromium, or set $CHROMIUM)")
        self.size, self.timeout_s = (width, height), timeout_s
        self._ids = itertools.count(1)
        self.proc = self.ws = None

    def __enter__(self) -> HeadlessBrowser:
        try:
            import websocket
        except ImportError as exc:
            raise BrowserError(
                "websocket-client is not installed (pip install websocket-client; the "
                "dev extra has it)"
            ) from exc

        self._profile = tempfile.mkdtemp(prefix="phantom-calib-chromium-")
        args = [
            self.executable,
            "--headless=new",
            "--remote-debugging-port=0",
            f"--user-data-dir={self._profile}",
            f"--window-size={self.size[0]},{self.size[1]}",
            "--no-first-run",
            "--no-default-browser-check",
            "--disable-extensions",
            "--disable-background-networking",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--ignore-gpu-blocklist",
            "--no-sandbox",  # containers run as root, where the sandbox refuses to start
            "--disable-dev-shm-usage",  # small /dev/shm in containers
            "about:blank",
        ]
        # its output to a file in the profile: a pipe nobody reads stalls a chatty browser
        self._log = Path(self._profile) / "chromium.log"
        try:
            with self._log.open("wb") as log_file:
                self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=log_file)
        except OSError as exc:  # review AG: a bad $CHROMIUM said only "[Errno 2] ..."
            shutil.rmtree(self._profile, ignore_errors=True)
            named = " ($CHROMIUM)" if os.environ.get("CHROMIUM") == self.executable else ""
            raise BrowserError(f"cannot start {self.executable}{named}: {exc}") from exc
        try:
            self._connect(websocket)
        except BaseException:  # review AG: the browser was left running
            self.close()
            raise
        return self

    def _connect(self, websocket) -> None:
        port_file = Path(self._profile) / "DevToolsActivePort"
        t0 = time.monotonic()
        while not port_file.is_file() or not port_file.read_text().strip():
            if self.proc.poll() is not None:
                err = self._log.read_text(errors="replace")[-2000:]
                raise BrowserError(f"{self.executable} exited at start:\n{err}")
            if time.monotonic() - t0 > self.timeout_s:
                raise BrowserError(f"{self.executable}: no DevTools port after {self.timeout_s} s")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        try:  # review CE-5: a refused connection or no page was a traceback
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [t for t in json.load(r) if t["type"] == "page"]
            if not pages:
                raise BrowserError(f"{self.executable}: no page to drive (DevTools lists none)")
            self.ws = websocket.create_connection(
                pages[0]["webSocketDebuggerUrl"], timeout=self.timeout_s, suppress_origin=True
            )
        except (websocket.WebSocketException, OSError, ValueError) as exc:
            raise BrowserError(f"{self.executable}: cannot reach its DevTools ({exc})") from exc
        self.call("Page.enable")
        self.call("Runtime.enable")
        # review CE-1: under --headless=new the window size is the window's, and the page
        # was 1300 x 757 of a 1300 x 900 window; the page itself is sized here
        width, height = self.size
        self.call(
            "Emulation.setDeviceMetricsOverride",
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def call(self, method: str, **params) -> dict:
        """Send one DevTools command and return its ``result``.

        Raises
        ------
        BrowserError
            The command failed, or the page's socket timed out or closed (review CD-7:
            websocket-client's own exceptions escaped as tracebacks).
        """
        import websocket

        msg_id = next(self._ids)
        try:
            self.ws.send(json.dumps({"id": msg_id, "method": method, "params": params}))
            while True:
                text = self.ws.recv()
                if not text:  # review CE-5: a close frame reads as ""
                    raise websocket.WebSocketConnectionClosedException("the socket closed")
                msg = json.loads(text)
                if msg.get("id") == msg_id:
                    break
        except (websocket.WebSocketException, OSError, ValueError) as exc:
            why = str(exc) or type(exc).__name__
            raise BrowserError(f"{method}: no answer from the browser ({why})") from exc
        if "error" in msg:
            raise BrowserError(f"{method}: {msg['error']}")
        return msg["result"]

    def goto(self, url: str, *, ready: str = "window.viewer && window.viewer.ready") -> None:
        """Load ``url`` and wait for the promise ``ready`` to settle."""
        self.call("Page.navigate", url=url)
        t0 = time.monotonic()
        while self.evaluate("document.readyState") != "complete" or not self.evaluate(
            "!!(window.viewer)"
        ):
            if time.monotonic() - t0 > self.timeout_s:
                raise BrowserError(f"{url}: page did not load in {self.timeout_s} s")
            time.sleep(0.05)
        self.evaluate(ready)

    def evaluate(self, expression: str):
        """Evaluate JavaScript in the page (awaiting a promise); its JSON value."""
        res = self.call(
            "Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True
        )
        if "exceptionDetails" in res:
            d = res["exceptionDetails"]
            text = d.get("exception", {}).get("description") or d.get("text")
            raise BrowserError(f"page script failed: {text}")
        return res["result"].get("value")

    def screenshot(self, path: str | Path) -> Path:
        """Save a PNG of the page."""
        data = self.call("Page.captureScreenshot", format="png")["data"]
        path = Path(path)
        atomic_write(path, lambda tmp: tmp.write_bytes(base64.b64decode(data)))
        return path

    def close(self) -> None:
        """Close the page's socket and end the browser process it started."""
        if self.ws is not None:
            self.ws.close()
            self.ws = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(getattr(self, "_profile", ""), ignore_errors=True)

    def __exit__(self, *exc) -> None:
        self.close()
