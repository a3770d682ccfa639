"""The mapping buffer: encoder features of many views, each remembering its pixel, camera and target.

One layout for everything that feeds the head (augmented training images, novel views), so that
mapping.train_head samples them alike: feats (N, C) fp16, pixels (N, 2), view (N,) indexing per-view
w2c (V, 3, 4) and K (V, 3, 3), and target (N, 3) world coordinates (NaN where there is none).
"""

from __future__ import annotations

import numpy as np
import torch

from acesplat.core.geometry import invert_pose

Buffer = dict[str, torch.Tensor]


class BufferBuilder:
    """Collects the chosen cells of one view at a time; ``build`` stacks them into a Buffer."""

    def __init__(self) -> None:
        self._parts: dict[str, list] = {k: [] for k in ("feats", "pixels", "view", "target", "w2c", "K")}
        self.features = 0

    def add_view(
        self,
        feats: torch.Tensor,
        take: np.ndarray,
        pixels: np.ndarray,
        c2w: np.ndarray,
        K: np.ndarray,
        targets: np.ndarray | None = None,
    ) -> None:
        """Cells ``take`` (k,) of a view's features (C, h, w), at ``pixels`` (k, 2), with their targets (k, 3)."""
        c = feats.shape[0]
        p = self._parts
        p["feats"].append(feats.reshape(c, -1)[:, torch.from_numpy(take).to(feats.device)].T.to(torch.float16).cpu())
        p["pixels"].append(torch.from_numpy(np.asarray(pixels, dtype=np.float32)))
        p["view"].append(torch.full((take.size,), len(p["w2c"]), dtype=torch.int64))
        t = np.full((take.size, 3), np.nan, np.float32) if targets is None else np.asarray(targets, np.float32)
        p["target"].append(torch.from_numpy(t))
        p["w2c"].append(invert_pose(c2w)[:3].astype(np.float32))
        p["K"].append(np.asarray(K, dtype=np.float32))
        self.features += take.size

    def build(self) -> Buffer | None:
        """The stacked buffer, or None if no view was added."""
        p = self._parts
        if not p["feats"]:
            return None
        out = {k: torch.cat(p[k]) for k in ("feats", "pixels", "view", "target")}
        out["w2c"] = torch.from_numpy(np.stack(p["w2c"]))
        out["K"] = torch.from_numpy(np.stack(p["K"]))
        return out


def merge_buffers(a: Buffer, b: Buffer) -> Buffer:
    """One buffer holding the entries of both; b's view indices are shifted past a's views."""
    out = {k: torch.cat([a[k], b[k].to(a[k].device)]) for k in ("feats", "pixels", "target", "w2c", "K")}
    out["view"] = torch.cat([a["view"], b["view"].to(a["view"].device) + a["w2c"].shape[0]])
    return out
