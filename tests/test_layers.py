"""The floors of the house, read from every module's imports: nothing imports upward, nothing imports the
applications, and nothing below the training floor imports torch or onnx.

Floors, bottom to top: primitives (``acesplat.core``, then the primitive subpackages built on it) -> training
(``acesplat.scr``, then ``acesplat.splat``) -> ``export`` | ``edge`` and ``firmware_bridge`` (primitives only) ->
``acesplat.apps``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOP = ("acesplat", "edge", "export", "firmware_bridge")

CORE = {"acesplat", "acesplat.core"}
PRIMITIVES = CORE | {"acesplat.raster", "acesplat.align", "acesplat.splatcore", "acesplat.synth", "acesplat.importers"}
TRAINING = {"acesplat.scr", "acesplat.splat"}
EVERYTHING = PRIMITIVES | TRAINING | {"export", "edge", "firmware_bridge", "acesplat.apps"}

# What each package may import, besides itself.
ALLOWED: dict[str, set[str]] = {
    "acesplat": set(),
    "acesplat.core": {"acesplat"},
    **{p: CORE for p in PRIMITIVES - CORE},
    "acesplat.scr": PRIMITIVES,
    "acesplat.splat": PRIMITIVES | {"acesplat.scr"},
    "export": PRIMITIVES | TRAINING,
    "edge": PRIMITIVES,
    "firmware_bridge": PRIMITIVES,
    "acesplat.apps": EVERYTHING,
}
TORCH_FREE = PRIMITIVES | {"edge", "firmware_bridge"}
HEAVY = ("torch", "onnx", "onnxscript")


def package_of(module: str) -> str:
    """The floor package a dotted module belongs to (the longest key of ALLOWED that prefixes it)."""
    best = ""
    for p in ALLOWED:
        if (module == p or module.startswith(p + ".")) and len(p) > len(best):
            best = p
    return best


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in a file, function-local ones included."""
    mod = module_name(path)
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
            # `from acesplat import apps` names a package too
            out += [(node.lineno, f"{name}.{a.name}") for a in node.names if f"{name}.{a.name}" in ALLOWED]
    return out


def project_files() -> list[Path]:
    return sorted(p for top in TOP for p in (ROOT / top).rglob("*.py"))


def violations() -> list[str]:
    found = []
    for path in project_files():
        here = package_of(module_name(path))
        for line, name in imports_of(path):
            where = f"{path.relative_to(ROOT)}:{line}"
            if name.split(".")[0] in HEAVY and here in TORCH_FREE:
                found.append(f"{where}: {here} is below the training floor but imports {name}")
            if name.split(".")[0] not in TOP:
                continue
            there = package_of(name)
            if there == "acesplat.apps" and here != "acesplat.apps":
                found.append(f"{where}: imports the applications ({name})")
            elif there != here and there not in ALLOWED[here]:
                found.append(f"{where}: {here} may not import {name} ({there})")
    return found


def test_every_module_is_on_a_floor() -> None:
    orphans = [str(p.relative_to(ROOT)) for p in project_files() if package_of(module_name(p)) == ""]
    assert orphans == []


def test_no_import_runs_upward() -> None:
    assert violations() == []


@pytest.mark.parametrize(
    ("source", "where", "expected"),
    [
        ("import acesplat.apps.cli\n", "edge/fake.py", "imports the applications"),
        ("from acesplat.scr import network\n", "acesplat/core/fake.py", "may not import"),
        ("import torch\n", "acesplat/splatcore/fake.py", "below the training floor"),
        ("from export.checks import x\n", "edge/fake.py", "may not import"),
        ("from ..scr.network import x\n", "acesplat/raster/fake.py", "may not import"),
    ],
)
def test_the_checker_catches_an_upward_import(tmp_path, monkeypatch, source, where, expected) -> None:
    """The checker itself: a planted upward import is reported (the real tree is not touched)."""
    fake = ROOT / where
    monkeypatch.setattr(f"{__name__}.project_files", lambda: [fake], raising=True)
    real_read = Path.read_text
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: source if self == fake else real_read(self, *a, **k))
    assert any(expected in v for v in violations())
