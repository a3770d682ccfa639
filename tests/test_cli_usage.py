"""Usage errors of both programs are one line on stderr with exit code 2, never typer's boxed panel."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from acesplat.apps.cli import app as desktop
from acesplat.apps.edge_cli import app as edge

CASES = [
    (desktop, ["demo", "--map-steps", "0"], "--map-steps"),  # out of range
    (desktop, ["demo", "--splat-iterations", "-1"], "--splat-iterations"),
    (desktop, ["map", "--steps", "0", "scene"], "--steps"),
    (desktop, ["eval", "--bogus"], "--bogus"),  # unknown option
    (desktop, ["map"], "scene"),  # missing argument
    (desktop, ["nosuchcommand"], "nosuchcommand"),
    (edge, ["replay", "b", "s", "--budget-ms", "abc"], "--budget-ms"),  # not a number
    (edge, ["bridge", "send-test", "--nosuchflag"], "--nosuchflag"),  # a sub-program's command
]


@pytest.mark.parametrize(("program", "args", "names"), CASES, ids=[" ".join(c[1]) for c in CASES])
def test_usage_errors_are_one_line(program, args, names) -> None:
    r = CliRunner().invoke(program, args)
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 2, r.output
    assert len(lines) == 1 and lines[0].startswith("error: ") and names in lines[0], r.output
    assert "╭" not in r.output and "Traceback" not in r.output


@pytest.mark.parametrize("program", [desktop, edge])
def test_help_still_prints(program) -> None:
    r = CliRunner().invoke(program, ["--help"])
    assert r.exit_code == 0 and "Usage" in r.output
    bare = CliRunner().invoke(program, [])  # no arguments: the help, as before
    assert "Usage" in bare.output and "error:" not in bare.output
