"""The edge install stays light: edge, firmware_bridge and every primitive package import with torch and onnx made
unimportable."""

from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

BLOCKER = """
import importlib, pkgutil, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('torch', 'onnx', 'onnxscript'):
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
for name in sys.argv[1:]:
    importlib.import_module(name)
print('ok')
"""


def _modules(package: str) -> list[str]:
    pkg_dir = ROOT.joinpath(*package.split("."))
    names = [package]
    for info in pkgutil.walk_packages([str(pkg_dir)], prefix=package + "."):
        names.append(info.name)
    return names


def test_edge_side_imports_without_torch_or_onnx() -> None:
    packages = [
        "edge",
        "firmware_bridge",
        "acesplat.core",
        "acesplat.raster",
        "acesplat.align",
        "acesplat.splatcore",
        "acesplat.synth",
        "acesplat.importers",
    ]
    modules = ["acesplat"] + [m for p in packages for m in _modules(p)]
    out = subprocess.run([sys.executable, "-c", BLOCKER, *modules], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
