"""One home per knob: a config dataclass field holds its default and a one-line reason.

``knob(default, "reason")`` declares a field; the command-line programs read the default and the help text from
the field (``acesplat.apps.support.option``), so a knob is written once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

HELP = "help"


def knob(default: Any = dataclasses.MISSING, reason: str = "", *, factory: Callable[[], Any] | None = None) -> Any:
    """A dataclass field with its default (or ``factory``) and the one-line reason shown as CLI help."""
    if not reason or "\n" in reason:
        raise ValueError(f"a knob needs a one-line reason, got {reason!r}")
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata={HELP: reason})
    return dataclasses.field(default=default, metadata={HELP: reason})


def knob_field(cls: type, name: str) -> dataclasses.Field:
    """The field ``name`` of the dataclass ``cls``; KeyError naming the class if it has none."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f
    raise KeyError(f"{cls.__name__} has no knob {name!r}")


def knob_default(cls: type, name: str) -> Any:
    """The default of ``cls.name`` (a factory's value for mutable defaults)."""
    f = knob_field(cls, name)
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise KeyError(f"{cls.__name__}.{name} has no default")


def knob_help(cls: type, name: str) -> str:
    """The one-line reason of ``cls.name`` ('' if it was declared without one)."""
    return str(knob_field(cls, name).metadata.get(HELP, ""))
