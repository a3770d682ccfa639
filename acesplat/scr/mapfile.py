"""The map file: a scene-specific head (fp16) plus what is needed to use it and to trust it.

Holds only tensors and plain Python values, so it loads with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from acesplat import __version__
from acesplat.core.atomic import atomic_path
from acesplat.core.errors import InputError
from acesplat.scr.encoders import EncoderIdentity, file_sha256, load_encoder
from acesplat.scr.network import Encoder, Head, HeadConfig, SCRNetwork

MAP_FORMAT = "acesplat-map"
MAP_VERSION = 1


@dataclass
class SceneMap:
    head: Head
    encoder_identity: EncoderIdentity
    mean: np.ndarray
    short_side: int
    metadata: dict = field(default_factory=dict)

    def network(self, encoder: Encoder) -> SCRNetwork:
        return SCRNetwork(encoder, self.head).eval()


def save_map(path: str | Path, m: SceneMap) -> None:
    head_sd = {k: (v.half() if v.is_floating_point() and k != "mean" else v) for k, v in m.head.state_dict().items()}
    payload = {
        "format": MAP_FORMAT,
        "version": MAP_VERSION,
        "created_by": f"acesplat-edge {__version__}",
        "created_unix": time.time(),
        "head_state": head_sd,
        "head_config": m.head.cfg.as_dict(),
        "head_in_channels": m.head.in_channels,
        "encoder": m.encoder_identity.as_dict(),
        "mean": torch.as_tensor(m.mean, dtype=torch.float64),
        "short_side": int(m.short_side),
        "metadata": m.metadata,
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def load_map(path: str | Path) -> SceneMap:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "map file not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise InputError(path, f"not a loadable map file ({type(e).__name__})") from None
    if not isinstance(obj, dict) or obj.get("format") != MAP_FORMAT:
        raise InputError(path, "not an acesplat map file")
    if obj.get("version", 0) > MAP_VERSION:
        raise InputError(path, f"map format version {obj['version']} is newer than this program ({MAP_VERSION})")
    cfg = HeadConfig(**obj["head_config"])
    mean = obj["mean"].numpy()
    head = Head(torch.from_numpy(mean).float(), in_channels=int(obj["head_in_channels"]), cfg=cfg)
    head.load_state_dict({k: v.float() for k, v in obj["head_state"].items()})
    head.eval()
    ident = EncoderIdentity(**obj["encoder"])
    return SceneMap(head, ident, mean, int(obj["short_side"]), dict(obj.get("metadata", {})))


def encoder_for_map(m: SceneMap, map_path: str | Path, encoder_path: str | Path | None = None) -> Encoder:
    """Load the encoder a map was trained with, checking its hash.

    Looks at ``encoder_path`` if given, else the path recorded in the map, else the shipped default.
    """
    candidates = [Path(encoder_path)] if encoder_path else [Path(m.encoder_identity.path)]
    if not encoder_path:
        from acesplat.scr.encoders import DEFAULT_ENCODER

        candidates.append(DEFAULT_ENCODER)
    for c in candidates:
        if c.is_file() and file_sha256(c) == m.encoder_identity.sha256:
            enc, _ = load_encoder(c)
            if enc.cfg.out != m.head.in_channels:
                raise InputError(c, f"encoder gives {enc.cfg.out} features, map head expects {m.head.in_channels}")
            return enc
    where = encoder_path or m.encoder_identity.path
    raise InputError(
        map_path,
        f"map was trained with encoder '{m.encoder_identity.name}' (sha256 {m.encoder_identity.sha256[:12]}...), "
        f"not found or different at {where}; pass --encoder PATH",
    )
