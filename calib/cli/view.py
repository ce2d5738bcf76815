"""The browser view: ``phantom-calib view WORK [--model MODEL.pt] [--port 8050] [--scan SCAN]``.

Also ``--screenshot PNG``: save the page with headless Chromium and exit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .app import app, fail

DEFAULT_PORT = 8050
#: Ports a browser refuses to fetch from: the "bad ports" of the Fetch standard
#: (https://fetch.spec.whatwg.org/#port-blocking), which Chromium applies.
BROWSER_BAD_PORTS = frozenset(
    [1, 7, 9, 11, 13, 15, 17, 19, 20, 21, 22, 23, 25, 37, 42, 43, 53, 69, 77, 79, 87, 95]
    + [101, 102, 103, 104, 109, 110, 111, 113, 115, 117, 119, 123, 135, 137, 139, 143, 161]
    + [179, 389, 427, 465, 512, 513, 514, 515, 526, 530, 531, 532, 540, 548, 554, 556, 563]
    + [587, 601, 636, 989, 990, 993, 995, 1719, 1720, 1723, 2049, 3659, 4045, 4190, 5060]
    + [5061, 6000, 6566, 6665, 6666, 6667, 6668, 6669, 6679, 6697, 10080]
)


@app.command()
def view(
    work: Annotated[
        Path, typer.Argument(metavar="WORK", help="A work folder (`calibrate` output).")
    ],
    model: Annotated[
        Path | None,
        typer.Option("--model", help="Surrogate (.pt, `surrogate train`): turn gravity freely."),
    ] = None,
    port: Annotated[
        int | None,
        typer.Option(
            "--port",
            help="TCP port on 127.0.0.1 (0: any free one). Default 8050; with --screenshot, "
            "any free one.",
        ),
    ] = None,
    scan: Annotated[
        str | None,
        typer.Option(
            "--scan", metavar="SCAN", help="Open at this scan's posture, its error map overlaid."
        ),
    ] = None,
    screenshot: Annotated[
        Path | None,
        typer.Option(
            "--screenshot",
            help="Save a PNG of the page with headless chromium and exit (no server left).",
        ),
    ] = None,
) -> None:
    """Serve a real-time 3-D view of the phantom on http://127.0.0.1:PORT/ (offline)."""
    import threading
    from urllib.parse import quote

    import nn

    from ..viewer import PortInUseError, SurfaceModelMismatchError, load_scene, make_server

    if port is None:  # review CD-3: a screenshot failed where a view held port 8050
        port = 0 if screenshot is not None else DEFAULT_PORT
    if not 0 <= port <= 65535:  # before any work (a bind error was a traceback)
        fail(ValueError(f"--port must lie in 0-65535, got {port}"))
    if port in BROWSER_BAD_PORTS:  # review CD-3: --port 22 timed out after 30 s
        fail(
            ValueError(
                f"--port {port}: browsers refuse to load pages from this port (a "
                f'"bad port" of the Fetch standard); choose another, e.g. {DEFAULT_PORT}'
            )
        )
    if screenshot is not None:  # review AG: checked only after the browser had run
        if screenshot.suffix.lower() != ".png":
            fail(ValueError(f"--screenshot {screenshot}: a .png file (it saves PNG data)"))
        if screenshot.is_dir() or not screenshot.parent.is_dir():
            fail(ValueError(f"--screenshot {screenshot}: not a file in an existing folder"))
    expected = (PortInUseError, SurfaceModelMismatchError, nn.SurrogateFileError, OSError)
    try:
        scene = load_scene(work, model)
    except expected as exc:
        fail(exc)
    names = [s["name"] for s in scene.info.get("scans", [])]
    if scan is not None and scan not in names:  # before a port is opened
        # review AG: a folder without scans (no calibration) let any --scan through;
        # review CD-4: and why it has none (a file that could not be read back)
        choose = f"choose from {names}" if names else "it has no calibrated scans"
        why = f" ({scene.missing[0]})" if scene.missing and not names else ""
        fail(ValueError(f"--scan {scan!r}: no such scan in {work}; {choose}{why}"))
    if screenshot is not None and scene.faces is None:  # review AX: an empty PNG, exit 0
        fail(ValueError(f"--screenshot: nothing to draw in {work}: {'; '.join(scene.missing)}"))
    try:
        server = make_server(scene, port=port)
    except expected as exc:
        fail(exc)
    url = server.url if scan is None else f"{server.url}?scan={quote(scan)}"
    shot_url = url + ("&" if "?" in url else "?") + "aa=1"  # antialiased, also in software
    for line in scene.missing:
        typer.secho(f"note: {line}", fg=typer.colors.YELLOW, err=True)
    if screenshot is not None:
        from ..viewer.headless import BrowserError, HeadlessBrowser

        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            # review CD-11: tall enough for the panel's marker key
            with HeadlessBrowser(width=1300, height=900) as browser:
                browser.goto(shot_url)
                # review CD-1: a page that failed (no WebGL2) was saved, exit 0
                error = browser.evaluate("window.viewer.error")
                if error:
                    raise BrowserError(f"the page failed, nothing saved: {error}")
                browser.screenshot(screenshot)
        except (BrowserError, OSError) as exc:
            fail(exc)
        finally:
            server.shutdown()
            server.server_close()
        typer.echo(f"wrote {screenshot}")
        return
    typer.echo(f"phantom-calib view: open {url}  (Ctrl-C to stop)")
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
