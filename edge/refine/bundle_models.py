"""The refinement models a bundle may carry (written by export/splat_export.py), torch-free.

Roles in the manifest's file list (acesplat/splatcore/bundle_section.py): ``gaussians`` (the scene's 3DGS PLY)
and ``splat_init_fp32`` (the Gaussian initializer: feature adapter + init head in one ONNX graph, fed the SCR
graph's features). The manifest's ``splat`` section says how to use them.
"""

from __future__ import annotations

from acesplat.core.bundle import Bundle, verify_file
from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians
from acesplat.core.ply import read_ply
from acesplat.splatcore.bundle_section import ROLE_GAUSSIANS


def bundle_gaussians(bundle: Bundle) -> Gaussians | None:
    """The bundle's Gaussians (verified against the manifest), or None when it was exported without --splat."""
    if not bundle.has(ROLE_GAUSSIANS):
        return None
    f = bundle.files[ROLE_GAUSSIANS]
    verify_file(bundle.root, f)
    return read_ply(bundle.root / f.path)


def no_models_message(bundle: Bundle) -> str:
    return (
        f"{bundle.root}: bundle has no Gaussian model (gaussians.ply); --refine is off and localization runs on "
        "(re-export with `acesplat export MAP --splat SPLAT`)"
    )


def splat_section(bundle: Bundle) -> dict:
    s = bundle.manifest.get("splat")
    if s is None:
        return {}
    if not isinstance(s, dict):
        raise InputError(bundle.root / "manifest.json", "'splat' section must be an object")
    return s
