"""`acesplat-edge`: the onboard program (localize, replay, profile, record, bridge)."""

from __future__ import annotations

import typer

from firmware_bridge.cli import app as bridge_app

app = typer.Typer(no_args_is_help=True, add_completion=False, help="ACEsplat onboard: localize against a bundle.")


@app.callback()
def _root() -> None:
    """ACEsplat onboard: localize against a bundle."""


app.add_typer(bridge_app, name="bridge")


def main() -> None:
    app()
