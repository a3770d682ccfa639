"""The export's knobs, apart from the exporter so the command line reads them without importing onnx."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from acesplat.core.config import knob


@dataclass
class ExportOptions:
    int8: bool = knob(False, "Also write a statically quantized INT8 model.")
    size_hw: tuple[int, int] | None = knob(
        None, "Input size HxW (default: the map's short side, training aspect ratio)."
    )
    encoder_path: Path | None = knob(None, "Encoder weights if not where the map says.")
    scene_path: Path | None = knob(None, "Scene folder if not where the map says (calibration and checks).")
    calibration_frames: int = knob(
        32, "Training images that calibrate the INT8 ranges (evenly spaced); more barely moves MinMax ranges."
    )
    dense: bool = knob(
        False,
        "Coordinates every 4th pixel instead of every 8th (as `acesplat eval --dense`): "
        "more accurate poses at about 3.5x the SCR time; no --splat.",
    )
    keyframes: bool = knob(
        False,
        "Carry the training images with their depth, so the edge can "
        "refine poses against them (acesplat-edge replay/localize --align).",
    )
