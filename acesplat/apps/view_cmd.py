"""`acesplat view`: a splat's Gaussians or a map's SCR point cloud, with the mapping cameras, in the browser."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from acesplat.apps.support import CountProgress, one_line_errors, option, stop_on_signals
from acesplat.core.viewer import ViewConfig, ViewScene, check_port_free, page_url, serve, view_kind


def load_view_scene(path: Path, scene: Path | None, encoder: Path | None, max_points: int) -> ViewScene:
    """The scene `acesplat view` shows for ``path``: a splat folder, a 3DGS .ply or a map file."""
    from acesplat.core.ply import read_ply
    from acesplat.core.scene import TRAIN, read_split
    from acesplat.core.viewer import SPLAT_PLY, splat_view

    kind = view_kind(path)
    if kind == "map":
        from acesplat.scr.map_view import map_view

        with CountProgress("predicting") as progress:
            return map_view(path, scene, encoder, max_points, progress)
    note = ""
    if kind == "splat":
        from acesplat.splat.splatfile import MANIFEST_NAME, load_manifest

        recorded = load_manifest(path).get("scene") if (path / MANIFEST_NAME).exists() else None
        g = read_ply(path / SPLAT_PLY)
        if scene is None and recorded and not Path(recorded).is_dir():
            note = f"no cameras: the splat's scene {recorded} is not there (pass --scene)"
        elif scene is None and recorded:
            scene = Path(recorded)
    else:
        g = read_ply(path)
    split = read_split(scene, TRAIN) if scene is not None else None
    view = splat_view(g, f"splat {path.name}", split, max_points)
    view.note = "; ".join(n for n in (view.note, note) if n)
    return view


@one_line_errors
def view_command(
    path: Path = typer.Argument(
        ..., help="A splat folder from `acesplat splat`, a 3DGS .ply, or a map file from `acesplat map`."
    ),
    scene: Path | None = typer.Option(
        None, help="Scene folder whose training cameras to show (default: the one the splat or map records)."
    ),
    port: int = option(ViewConfig, "port"),
    host: str = option(ViewConfig, "host"),
    max_points: int = option(ViewConfig, "max_points"),
    encoder: Path | None = typer.Option(None, help="A map's encoder weights if not where the map says."),
) -> None:
    """Serve a viser page with the Gaussians (or a map's SCR point cloud) and the mapping cameras; Ctrl-C stops."""
    stop_on_signals()
    cfg = ViewConfig(host=host, port=port, max_points=max_points)
    check_port_free(cfg.host, cfg.port)  # before the map's predictions, which take a while
    view = load_view_scene(path, scene, encoder, cfg.max_points)
    server, counts = serve(view, cfg.host, cfg.port)
    shown = ", ".join(f"{v} {k}" for k, v in counts.items() if v or k == "cameras")
    note = f" ({view.note})" if view.note else ""
    print(f"viewing {path}: {shown}{note} at {page_url(cfg.host, server.get_port())} (Ctrl-C stops)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        stop_within(server, STOP_SECONDS)


STOP_SECONDS = 5.0
"""Ctrl-C ends the viewer within this long even when viser's server thread does not stop (a client mid-handshake)."""


def stop_within(server, seconds: float) -> None:
    """Stop the viser server; if it has not stopped after ``seconds``, end the process (exit 0: the user asked)."""
    import os
    import threading

    t = threading.Thread(target=server.stop, daemon=True)
    t.start()
    t.join(seconds)
    if t.is_alive():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
