"""The splat folder: ``gaussians.ply`` (standard 3DGS layout), the adapter and init head weights,
and ``splat.json`` (how it was made, and what a renderer needs: resolution, background).

Weights are saved as plain state dicts with their configs as plain values, so they load with
``torch.load(weights_only=True)``: a splat folder from elsewhere cannot run code on load.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from acesplat import __version__
from acesplat.core.atomic import atomic_path, write_json
from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians
from acesplat.core.ply import read_ply, write_ply
from acesplat.splat.adapter import AdapterConfig
from acesplat.splat.init_head import InitHeadConfig
from acesplat.splat.instantiate import GaussianInitializer

SPLAT_FORMAT = "acesplat-splat"
SPLAT_VERSION = 1
PLY_NAME = "gaussians.ply"
ADAPTER_NAME = "adapter.pt"
HEAD_NAME = "init_head.pt"
MANIFEST_NAME = "splat.json"


def save_splat(out_dir: str | Path, g: Gaussians, init: GaussianInitializer, manifest: dict) -> None:
    """Write the four files (each atomically)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / PLY_NAME, g)
    for name, module, cfg in (
        (ADAPTER_NAME, init.adapter, init.adapter.cfg.as_dict()),
        (HEAD_NAME, init.head, init.head.cfg.as_dict()),
    ):
        payload = {
            "format": SPLAT_FORMAT,
            "version": SPLAT_VERSION,
            "config": cfg,
            "state_dict": {k: v.detach().cpu().clone() for k, v in module.state_dict().items()},
        }
        with atomic_path(out / name) as tmp:
            torch.save(payload, tmp)
    write_json(
        out / MANIFEST_NAME,
        {"format": SPLAT_FORMAT, "version": SPLAT_VERSION, "created_by": f"acesplat-edge {__version__}", **manifest},
    )


def load_manifest(splat_dir: str | Path) -> dict:
    d = Path(splat_dir)
    if not d.is_dir():
        raise InputError(d, "splat folder does not exist")
    p = d / MANIFEST_NAME
    try:
        m = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError(p, "missing (not a splat folder from `acesplat splat`?)") from None
    except (OSError, ValueError) as e:
        raise InputError(p, f"cannot read splat manifest ({e})") from None
    if not isinstance(m, dict) or m.get("format") != SPLAT_FORMAT:
        raise InputError(p, "not an acesplat splat manifest")
    if int(m.get("version", 0)) > SPLAT_VERSION:
        raise InputError(p, f"splat format version {m['version']} is newer than this program ({SPLAT_VERSION})")
    for key in ("short_side", "background"):
        if key not in m:
            raise InputError(p, f"manifest has no '{key}'")
    return m


def load_gaussians(splat_dir: str | Path) -> Gaussians:
    return read_ply(Path(splat_dir) / PLY_NAME)


def load_initializer(splat_dir: str | Path) -> GaussianInitializer:
    """The adapter and init head of a splat folder (weights only)."""
    d = Path(splat_dir)
    parts = {}
    for name in (ADAPTER_NAME, HEAD_NAME):
        p = d / name
        if not p.is_file():
            raise InputError(p, "weights file missing")
        try:
            obj = torch.load(p, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises several types for corrupt or pickled-object files
            raise InputError(p, f"cannot load weights safely ({type(e).__name__})") from None
        if not isinstance(obj, dict) or obj.get("format") != SPLAT_FORMAT or "state_dict" not in obj:
            raise InputError(p, "not an acesplat splat weights file")
        parts[name] = obj
    a_cfg = AdapterConfig.from_dict(parts[ADAPTER_NAME]["config"])
    h_cfg = InitHeadConfig(**parts[HEAD_NAME]["config"])
    init = GaussianInitializer(a_cfg, h_cfg)
    try:
        init.adapter.load_state_dict(parts[ADAPTER_NAME]["state_dict"])
        init.head.load_state_dict(parts[HEAD_NAME]["state_dict"])
    except RuntimeError as e:
        raise InputError(d, f"weights do not match their configs ({str(e).splitlines()[0]})") from None
    return init.eval()
