"""The export's knobs, apart from the exporter so the command line reads them without importing onnx."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from acesplat.core.config import knob
from acesplat.core.errors import InputError

INT8_FORMATS = ("qdq", "qoperator")
"""onnxruntime's two quantized graph forms: QuantizeLinear/DequantizeLinear pairs, or QLinear* operators."""
INT8_TYPES = ("u8s8", "s8s8", "u8u8")
"""Activation and weight integer types (u = uint8, s = int8), activations first."""
INT8_CALIBRATIONS = ("minmax", "percentile", "entropy")
"""onnxruntime's ways of turning the calibration images' activations into INT8 ranges."""


@dataclass
class ExportOptions:
    int8: bool = knob(False, "Also write a statically quantized INT8 model.")
    size_hw: tuple[int, int] | None = knob(
        None, "Input size HxW (default: the map's short side, training aspect ratio)."
    )
    encoder_path: Path | None = knob(None, "Encoder weights if not where the map says.")
    scene_path: Path | None = knob(None, "Scene folder if not where the map says (calibration and checks).")
    calibration_frames: int = knob(32, "Training images that calibrate the INT8 ranges (evenly spaced).")
    int8_calibration: str = knob(
        "percentile",
        "INT8 activation ranges from the calibration images: minmax, percentile (clips the rarest activations, "
        "closer to FP32 than minmax: bench/int8_format.md) or entropy.",
    )
    int8_percentile: float = knob(
        99.999, "Share (%) of each activation's calibration values the percentile range keeps (onnxruntime's default)."
    )
    int8_format: str = knob("qdq", "INT8 graph form: qdq or qoperator (bench/int8_format.md).")
    int8_types: str = knob(
        "u8u8", "INT8 activation/weight types: u8s8, s8s8 or u8u8 (least FP32 deviation on AVX2: bench/int8_format.md)."
    )
    int8_vnni: bool = knob(
        True,
        "With --int8, also a U8S8 INT8 graph: about 2x faster on CPUs with VNNI or AMX, where `--int8` picks it "
        "after the device's check; it saturates without VNNI and the check keeps the default there "
        "(bench/int8_format.md).",
    )
    int8_per_channel: bool = knob(True, "One INT8 weight scale per output channel (bench/int8_format.md).")
    int8_reduce_range: bool = knob(
        False, "7-bit weights, which cannot saturate U8S8 products on CPUs without VNNI (bench/int8_format.md)."
    )
    check_frames: int = knob(
        4, "Test (else training) frames stored with their FP32 coordinates for `acesplat-edge check`."
    )
    dense: bool = knob(
        False,
        "Coordinates every 4th pixel instead of every 8th (as `acesplat eval --dense`): "
        "more accurate poses at about 3.5x the SCR time; no --splat.",
    )
    encoder_rank: int = knob(
        0,
        "0 keeps the encoder exact; R > 0 runs its last 3x3 layer through R channels fitted to the training "
        "images: at 128, a fifth less SCR inference for a few % of the test cells (bench/encoder_rank.md).",
    )
    keyframes: bool = knob(
        False,
        "Carry the training images with their depth, so the edge can "
        "refine poses against them (acesplat-edge replay/localize --align).",
    )


def int8_scheme_text(opts: ExportOptions) -> str:
    """The INT8 scheme in words, as the manifest records it."""
    return (
        f"onnxruntime static {opts.int8_format.upper()}, "
        f"{'per-channel' if opts.int8_per_channel else 'per-tensor'} weights, {opts.int8_types.upper()}"
        f"{', reduce_range' if opts.int8_reduce_range else ''}, {_calibration_text(opts)} calibration, "
        "first and last convs and head tail in float; "
        "features output dequantized"
    )


def _calibration_text(opts: ExportOptions) -> str:
    return f"percentile {opts.int8_percentile:g}%" if opts.int8_calibration == "percentile" else opts.int8_calibration


def vnni_options(opts: ExportOptions) -> ExportOptions | None:
    """The options of the U8S8 twin (``int8_vnni``), or None when it is not written (no --int8, turned off, or the
    default graph is U8S8 already)."""
    if not (opts.int8 and opts.int8_vnni) or opts.int8_types == "u8s8":
        return None
    return replace(opts, int8_types="u8s8", int8_reduce_range=False)


def check_int8_options(opts: ExportOptions) -> None:
    """InputError in one line, naming the choices, when an INT8 knob has an unknown value."""
    if opts.int8_format not in INT8_FORMATS:
        raise InputError(None, f"--int8-format must be one of {', '.join(INT8_FORMATS)}, got {opts.int8_format!r}")
    if opts.int8_types not in INT8_TYPES:
        raise InputError(None, f"--int8-types must be one of {', '.join(INT8_TYPES)}, got {opts.int8_types!r}")
    if opts.int8_calibration not in INT8_CALIBRATIONS:
        raise InputError(
            None, f"--int8-calibration must be one of {', '.join(INT8_CALIBRATIONS)}, got {opts.int8_calibration!r}"
        )
    if not 50.0 < opts.int8_percentile <= 100.0:
        raise InputError(None, f"--int8-percentile must be above 50 and at most 100, got {opts.int8_percentile}")
    if opts.check_frames < 0:
        raise InputError(None, f"--check-frames must be non-negative, got {opts.check_frames}")
