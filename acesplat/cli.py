"""`acesplat`: the desktop program (synth, map, eval, splat, render, export, demo)."""

from __future__ import annotations

import typer

from .importers.cli_cmd import import_command
from .demo import demo_command
from .scr.cli_cmds import eval_command, map_command, pretrain_command
from .splat.cli_cmds import render_command, splat_command
from .synth.cli_cmd import synth_command
from export.cli_cmd import export_command  # the CLI is the top layer, so it may reach up to export/

app = typer.Typer(no_args_is_help=True, add_completion=False, help="ACEsplat desktop: make maps and splats, export bundles.")


@app.callback()
def _root() -> None:
    """ACEsplat desktop: make maps and splats, export bundles."""


app.command("synth")(synth_command)
app.command("import")(import_command)
app.command("map")(map_command)
app.command("demo")(demo_command)
app.command("eval")(eval_command)
app.command("pretrain-encoder")(pretrain_command)
app.command("splat")(splat_command)
app.command("render")(render_command)
app.command("export")(export_command)


def main() -> None:
    app()
