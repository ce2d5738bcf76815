"""``phantom-calib view WORK [--model MODEL.pt] [--port 8050]``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .app import app, fail


@app.command()
def view(
    work: Annotated[
        Path, typer.Argument(metavar="WORK", help="A work folder (`calibrate` output).")
    ],
    model: Annotated[
        Path | None,
        typer.Option("--model", help="Surrogate (.pt, `surrogate train`): turn gravity freely."),
    ] = None,
    port: Annotated[int, typer.Option("--port", help="TCP port on 127.0.0.1.")] = 8050,
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

    if not 0 <= port <= 65535:  # before any work (a bind error was a traceback)
        fail(ValueError(f"--port must lie in 0-65535, got {port}"))
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
        # review AG: a folder without scans (no calibration) let any --scan through
        choose = f"choose from {names}" if names else "it has no calibrated scans"
        fail(ValueError(f"--scan {scan!r}: no such scan in {work}; {choose}"))
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
            with HeadlessBrowser() as browser:
                browser.goto(shot_url)
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
