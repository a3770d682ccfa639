"""Shared plumbing for the two command-line programs: one-line errors, JSON reports."""

from __future__ import annotations

import functools
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import typer
from typer.core import TyperGroup

from acesplat.core.atomic import write_json
from acesplat.core.errors import InputError

F = TypeVar("F", bound=Callable[..., Any])


def one_line_errors(fn: F) -> F:
    """Turn InputError into a one-line message on stderr and exit code 2, with no traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except InputError as e:
            print(f"error: {e}", file=sys.stderr)
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def _usage_error_class() -> type[Exception]:
    """click's UsageError, whether typer ships click or vendors it (found through BadParameter's bases)."""
    for cls in typer.BadParameter.__mro__:
        if cls.__name__ == "UsageError":
            return cls
    return typer.BadParameter  # pragma: no cover - every click has BadParameter(UsageError)


class OneLineUsageErrors(TyperGroup):
    """A program whose usage errors (an option out of range, an unknown flag, a missing argument) are one line.

    typer prints them as a boxed multi-line panel; the house prints every bad input as ``error: ...`` on
    stderr with exit code 2. Running with no arguments still prints the help.
    """

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        usage_error = _usage_error_class()
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except usage_error as e:
            if type(e).__name__ == "NoArgsIsHelpError":  # no arguments: the help, as typer would print it
                return super().main(*args, standalone_mode=True, **kwargs)
            ctx = getattr(e, "ctx", None)
            hint = f" (see {ctx.command_path} --help)" if ctx is not None else ""
            message = " ".join(e.format_message().split())  # type: ignore[attr-defined]
            print(f"error: {message}{hint}", file=sys.stderr)
            sys.exit(2)
        except typer.Abort:
            print("Aborted!", file=sys.stderr)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def stop_on_signals() -> None:
    """Make Ctrl-C (SIGINT) and SIGTERM end a serve-until-stopped command through its cleanup.

    A process started with SIGINT ignored (a background job of a non-interactive shell) would otherwise keep
    ignoring the Ctrl-C its parent forwards, and SIGTERM (systemd, docker stop) would end it without finalizing
    its outputs. No-op off the main thread, where Python cannot install handlers.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _interrupt)


def report_json(path: Path | None, payload: dict[str, Any]) -> None:
    """Write a command's numbers to ``--json PATH`` atomically (no-op without the flag)."""
    if path is not None:
        write_json(path, payload)


def parse_size(text: str) -> tuple[int, int]:
    """'HxW' -> (H, W)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(None, f"size must look like HxW (e.g. 240x320), got {text!r}") from None
    if h <= 0 or w <= 0:
        raise InputError(None, f"size must be positive, got {text!r}")
    return h, w


def parse_int_pair(text: str, requirement: str) -> tuple[int, int]:
    """'A,B' -> (A, B); ``requirement`` opens the one-line error (e.g. "--views must be ... like 10,14")."""
    try:
        a, b = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(None, f"{requirement}, got {text!r}") from None
    return a, b


class PhaseProgress:
    """A rich progress bar with one task per named phase, driven by (phase, fraction, info) callbacks."""

    def __init__(self, description: str = "") -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.percentage:>5.1f}%"),
            TimeElapsedColumn(),
            TextColumn("{task.fields[info]}"),
            transient=False,
        )
        self._tasks: dict[str, int] = {}
        self._prefix = description

    def __enter__(self) -> PhaseProgress:
        self._progress.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._progress.__exit__(*exc)

    def __call__(self, phase: str, fraction: float, info: dict | None = None) -> None:
        if phase not in self._tasks:
            self._tasks[phase] = self._progress.add_task(f"{self._prefix}{phase}", total=1.0, info="")
        text = "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in (info or {}).items())
        self._progress.update(self._tasks[phase], completed=min(max(fraction, 0.0), 1.0), info=text)


class CountProgress:
    """A rich bar driven by (done, total) callbacks that appears only at the first item, so an input error raised
    before any work stays one clean line on stderr; hidden when stderr is not a terminal."""

    def __init__(self, description: str) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        console = Console(stderr=True)
        self._progress = Progress(
            TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
            console=console, transient=True, disable=not console.is_terminal,
        )  # fmt: skip
        self._task = self._progress.add_task(description, total=None)

    def __enter__(self) -> CountProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self._progress.stop()

    def __call__(self, done: int, total: int) -> None:
        if done == 1:
            self._progress.start()
        self._progress.update(self._task, completed=done, total=total)


def option(cls: type, name: str, *param_decls: str, default: Any = ..., **kwargs: Any) -> Any:
    """A typer option whose default and help come from the knob ``cls.name`` (acesplat.core.config.knob).

    ``default=None`` keeps the knob's value out of the signature (an optional override, e.g. a value computed
    from the scene); the help then names the knob's default.
    """
    from acesplat.core.config import knob_default, knob_help

    value = knob_default(cls, name)
    text = kwargs.pop("help", None) or knob_help(cls, name)
    if default is None:
        return typer.Option(None, *param_decls, help=f"{text} (default: {value})", **kwargs)
    return typer.Option(value, *param_decls, help=text, **kwargs)
