"""LPIPS (Zhang et al. 2018, AlexNet variant, v0.1) from weight files the user already has.

Nothing is downloaded. Two files are needed: torchvision's AlexNet weights (``features.*`` keys, e.g.
``alexnet-owt-7be5be79.pth``) and the LPIPS linear layers (``lin0.model.1.weight`` .. ``lin4...``,
the lpips package's ``weights/v0.1/alex.pth``). One file holding both sets of keys also works.
Both load with ``weights_only=True``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from acesplat.core.errors import InputError

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
"""LPIPS's input scaling of [-1, 1] images."""
ALEX_CONVS = {
    0: (3, 64, 11, 4, 2),
    3: (64, 192, 5, 1, 2),
    6: (192, 384, 3, 1, 1),
    8: (384, 256, 3, 1, 1),
    10: (256, 256, 3, 1, 1),
}
"""torchvision AlexNet ``features`` index -> (in, out, kernel, stride, padding)."""
TAP_CHANNELS = (64, 192, 384, 256, 256)


class LPIPSAlex(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleDict(
            {str(i): nn.Conv2d(c_in, c_out, k, s, p) for i, (c_in, c_out, k, s, p) in ALEX_CONVS.items()}
        )
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in TAP_CHANNELS)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    def taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs LPIPS compares (x: (B, 3, H, W) in [-1, 1])."""
        x = (x - self.shift) / self.scale
        c = self.convs
        r1 = F.relu(c["0"](x))
        r2 = F.relu(c["3"](F.max_pool2d(r1, 3, 2)))
        r3 = F.relu(c["6"](F.max_pool2d(r2, 3, 2)))
        r4 = F.relu(c["8"](r3))
        r5 = F.relu(c["10"](r4))
        return [r1, r2, r3, r4, r5]

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """LPIPS distance (B,) of images (B, 3, H, W) in [-1, 1]."""
        total = a.new_zeros(a.shape[0])
        for fa, fb, lin in zip(self.taps(a), self.taps(b), self.lins):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((na - nb) ** 2).mean(dim=(1, 2, 3))
        return total


def _load(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, "LPIPS weights file not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt or pickled-object files
        raise InputError(path, f"cannot load weights safely ({type(e).__name__})") from None
    if not isinstance(obj, dict):
        raise InputError(path, "does not hold a state dict")
    return obj


def lpips_state_dict(sd: dict, where: Path | str) -> dict[str, torch.Tensor]:
    """Map torchvision / lpips key names onto :class:`LPIPSAlex`'s; InputError naming a missing key."""
    out = {}
    for i in ALEX_CONVS:
        for kind in ("weight", "bias"):
            key = f"features.{i}.{kind}"
            if key not in sd:
                raise InputError(where, f"missing AlexNet tensor {key}")
            out[f"convs.{i}.{kind}"] = sd[key]
    for j in range(len(TAP_CHANNELS)):
        key = f"lin{j}.model.1.weight"
        if key not in sd:
            raise InputError(where, f"missing LPIPS linear layer {key}")
        out[f"lins.{j}.weight"] = sd[key]
    return out


def load_lpips(*paths: str | Path) -> Callable[[torch.Tensor, torch.Tensor], float]:
    """A function (img, ref) -> LPIPS for images (H, W, 3) in [0, 1], from one or two weight files."""
    merged: dict = {}
    for p in paths:
        merged.update(_load(Path(p)))
    where = ", ".join(str(p) for p in paths)
    model = LPIPSAlex()
    try:
        model.load_state_dict({**lpips_state_dict(merged, where), "shift": model.shift, "scale": model.scale})
    except RuntimeError as e:
        raise InputError(where, f"LPIPS tensors have unexpected shapes ({str(e).splitlines()[0]})") from None
    model.eval()

    @torch.no_grad()
    def fn(img: torch.Tensor, ref: torch.Tensor) -> float:
        a = img.float().permute(2, 0, 1)[None] * 2 - 1
        b = ref.float().permute(2, 0, 1)[None] * 2 - 1
        return float(model(a, b)[0])

    return fn
