"""`acesplat-edge`: the onboard program (localize, replay, profile, record, check, bridge)."""

from __future__ import annotations

import typer

from acesplat.apps.bridge_cmd import app as bridge_app
from acesplat.apps.edge_cmd import check_command, localize_command, profile_command, record_command, replay_command
from acesplat.apps.support import OneLineUsageErrors

app = typer.Typer(
    cls=OneLineUsageErrors,
    no_args_is_help=True,
    add_completion=False,
    help="ACEsplat onboard: localize against a bundle.",
)


@app.callback()
def _root() -> None:
    """ACEsplat onboard: localize against a bundle."""


app.command("localize")(localize_command)
app.command("replay")(replay_command)
app.command("profile")(profile_command)
app.command("record")(record_command)
app.command("check")(check_command)
app.add_typer(bridge_app, name="bridge")


def main() -> None:
    app()
