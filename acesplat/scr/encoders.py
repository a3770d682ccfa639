"""Where encoder weights come from: the project's own shipped default, or a user's file (e.g. ACE's).

An encoder is identified by the sha256 of its weight file, so a map can refuse an encoder that is
not the one it was trained with.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import torch

from acesplat.core.errors import InputError
from acesplat.scr.network import Encoder

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
DEFAULT_ENCODER = WEIGHTS_DIR / "encoder_default.pt"
ENCODER_KEYS = (
    "conv1",
    "conv2",
    "conv3",
    "conv4",
    "res1_conv1",
    "res1_conv2",
    "res1_conv3",
    "res2_conv1",
    "res2_conv2",
    "res2_conv3",
    "res2_skip",
)


@dataclass(frozen=True)
class EncoderIdentity:
    name: str
    sha256: str
    path: str

    def as_dict(self) -> dict[str, str]:
        return {"name": self.name, "sha256": self.sha256, "path": self.path}


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_encoder_state(path: Path) -> dict[str, torch.Tensor]:
    """A state dict with ACE's encoder names; accepts a bare state dict or {'encoder': state_dict}."""
    if not path.is_file():
        raise InputError(path, "encoder weights not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt or pickled-object files
        raise InputError(path, f"cannot load encoder weights safely ({type(e).__name__})") from None
    if isinstance(obj, dict) and "encoder" in obj and isinstance(obj["encoder"], dict):
        obj = obj["encoder"]
    if not isinstance(obj, dict):
        raise InputError(path, "encoder file does not hold a state dict")

    def present(k: str) -> bool:
        # res2_conv3 may be factorized or separable (acesplat.scr.network): its two halves instead
        halves = [f"{k}.point", f"{k}.depth"] if f"{k}.point.weight" in obj else [f"{k}.reduce", f"{k}.expand"]
        names = [k] if f"{k}.weight" in obj else halves
        return all(f"{n}.weight" in obj and f"{n}.bias" in obj for n in names)

    missing = [k for k in ENCODER_KEYS if not present(k)]
    if missing:
        raise InputError(path, f"not an ACE-style encoder state dict (missing {', '.join(missing)})")
    return obj


def load_encoder(path: str | Path | None = None) -> tuple[Encoder, EncoderIdentity]:
    """The encoder at ``path`` (default: the project's shipped weights) and its identity."""
    p = Path(path) if path is not None else DEFAULT_ENCODER
    sd = load_encoder_state(p)
    try:
        enc = Encoder.from_state_dict(sd)
    except RuntimeError as e:
        raise InputError(p, f"encoder tensors have unexpected shapes ({str(e).splitlines()[0]})") from None
    enc.eval()
    name = "acesplat-default" if p.resolve() == DEFAULT_ENCODER.resolve() else p.name
    return enc, EncoderIdentity(name, file_sha256(p), str(p.resolve()))
