"""`acesplat`: the desktop program (synth, import, pose, map, demo, eval, pretrain-encoder, adapt-encoder, splat,
render, export, view)."""

from __future__ import annotations

import typer

from acesplat.apps.demo import demo_command
from acesplat.apps.export_cmd import export_command  # the CLI is the top layer, so it may reach up to export/
from acesplat.apps.import_cmd import import_command
from acesplat.apps.pose_cmd import pose_command
from acesplat.apps.scr_cmd import adapt_command, eval_command, map_command, pretrain_command
from acesplat.apps.splat_cmd import render_command, splat_command
from acesplat.apps.support import OneLineUsageErrors
from acesplat.apps.synth_cmd import synth_command
from acesplat.apps.view_cmd import view_command

app = typer.Typer(
    cls=OneLineUsageErrors,
    no_args_is_help=True,
    add_completion=False,
    help="ACEsplat desktop: make maps and splats, export bundles.",
)


@app.callback()
def _root() -> None:
    """ACEsplat desktop: make maps and splats, export bundles."""


app.command("synth")(synth_command)
app.command("import")(import_command)
app.command("pose")(pose_command)
app.command("map")(map_command)
app.command("demo")(demo_command)
app.command("eval")(eval_command)
app.command("pretrain-encoder")(pretrain_command)
app.command("adapt-encoder")(adapt_command)
app.command("splat")(splat_command)
app.command("render")(render_command)
app.command("export")(export_command)
app.command("view")(view_command)


def main() -> None:
    app()


if __name__ == "__main__":  # python -m acesplat.apps.cli, and torchrun -m acesplat.apps.cli
    main()
