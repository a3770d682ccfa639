"""The torch device a command runs on."""

from __future__ import annotations

from acesplat.core.errors import InputError


def resolve_device(device: str) -> str:
    """'auto' (CUDA when present), 'cpu' or 'cuda' -> the device name; InputError if it cannot be used."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError(None, "--device cuda asked for, but no CUDA device is available")
    if device not in ("cpu", "cuda"):
        raise InputError(None, f"--device must be auto, cpu or cuda, got {device!r}")
    return device
