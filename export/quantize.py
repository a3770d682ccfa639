"""Static INT8 quantization of the SCR graph with onnxruntime, in the scheme ExportOptions names (form, types,
per-channel, reduce_range; the default chosen in bench/int8_format.md). The head's residual block, fc1-fc3 and its
tail (homogeneous division, clamp, mean offset) stay in float: quantizing metric coordinates to 8 bits would cost
centimetres by itself (FLOAT_HEAD_CONVS). So do the encoder's first layers (FLOAT_LEAD_CONVS).
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_static,
)
from onnxruntime.quantization.shape_inference import quant_pre_process

from acesplat.core.atomic import atomic_path
from acesplat.core.config import knob_default
from export.onnx_graph import INPUT_NAME
from export.options import INT8_CALIBRATIONS, INT8_FORMATS, INT8_TYPES, ExportOptions

_CALIBRATIONS = dict(
    zip(
        INT8_CALIBRATIONS,
        (CalibrationMethod.MinMax, CalibrationMethod.Percentile, CalibrationMethod.Entropy),
        strict=True,
    )
)
_FORMATS = dict(zip(INT8_FORMATS, (QuantFormat.QDQ, QuantFormat.QOperator), strict=True))
_TYPES = dict(
    zip(
        INT8_TYPES,
        ((QuantType.QUInt8, QuantType.QInt8), (QuantType.QInt8, QuantType.QInt8), (QuantType.QUInt8, QuantType.QUInt8)),
        strict=True,
    )
)


class _Images(CalibrationDataReader):
    """Feeds grayscale uint8 images (H, W) as the graph's float input, one at a time, from the range onnxruntime's
    strided calibration sets (each stride's activations are reduced to ranges or histograms before the next)."""

    def __init__(self, images: Sequence[np.ndarray]) -> None:
        self._images = list(images)
        self._it = iter(self._images)

    def __len__(self) -> int:
        return len(self._images)

    def set_range(self, start_index: int, end_index: int) -> None:
        self._it = iter(self._images[start_index:end_index])

    def get_next(self) -> dict[str, np.ndarray] | None:
        img = next(self._it, None)
        if img is None:
            return None
        return {INPUT_NAME: np.ascontiguousarray(img, dtype=np.float32)[None, None]}


CALIBRATION_STRIDE = 1
"""Calibration images whose activations are held at once: one image's, where histogram calibration would otherwise
hold every image's (memory in bench/int8_format.md)."""


FLOAT_HEAD_CONVS = 6
"""Trailing convolutions kept in float: the head's residual block and fc1-fc3 (accuracy against latency in
bench/export.md)."""


FLOAT_LEAD_CONVS = 3
"""Leading convolutions kept in float: the encoder's first three, few channels at full to quarter resolution, where
INT8 saves no time and costs accuracy (bench/int8_format.md)."""


def conv_nodes_to_quantize(
    model: onnx.ModelProto, float_convs: int = FLOAT_HEAD_CONVS, float_lead: int = FLOAT_LEAD_CONVS
) -> list[str]:
    """Every Conv except the last ``float_convs`` (at least the head's output layer, whose result is divided into
    metres) and the first ``float_lead``."""
    convs = [n.name for n in model.graph.node if n.op_type == "Conv"]
    return convs[float_lead : len(convs) - float_convs]


def quantize_int8(
    fp32_path: str | Path,
    out_path: str | Path,
    calibration: list[np.ndarray],
    method: str = knob_default(ExportOptions, "int8_calibration"),
    float_tail: bool = True,
    float_convs: int = FLOAT_HEAD_CONVS,
    float_lead: int = FLOAT_LEAD_CONVS,
    quant_format: str = knob_default(ExportOptions, "int8_format"),
    types: str = knob_default(ExportOptions, "int8_types"),
    per_channel: bool = knob_default(ExportOptions, "int8_per_channel"),
    reduce_range: bool = knob_default(ExportOptions, "int8_reduce_range"),
    percentile: float = knob_default(ExportOptions, "int8_percentile"),
) -> Path:
    """Quantize the FP32 model at ``fp32_path`` using ``calibration`` grayscale images (H, W) uint8.

    ``float_tail=False`` quantizes the last convolution too; ``float_convs`` keeps that many trailing
    convolutions (the head's) in float (bench/export.md), ``float_lead`` that many leading ones (the encoder's).
    ``quant_format`` ('qdq' or 'qoperator'), ``types`` ('u8s8', 's8s8', 'u8u8': activations then weights),
    ``per_channel`` and ``reduce_range`` are onnxruntime's;
    ``method`` ('minmax', 'percentile', 'entropy') sets the activation ranges, ``percentile`` the share they keep.
    """
    if not calibration:
        raise ValueError("INT8 calibration needs at least one image")
    if quant_format not in _FORMATS:
        raise ValueError(f"quant_format must be one of {', '.join(_FORMATS)}, got {quant_format!r}")
    if method not in _CALIBRATIONS:
        raise ValueError(f"method must be one of {', '.join(_CALIBRATIONS)}, got {method!r}")
    if types not in _TYPES:
        raise ValueError(f"types must be one of {', '.join(_TYPES)}, got {types!r}")
    act_type, weight_type = _TYPES[types]
    out_path = Path(out_path)
    with tempfile.TemporaryDirectory() as td:
        pre = Path(td) / "pre.onnx"
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        model = onnx.load(str(pre))
        # onnxruntime's histogram calibrators print a line per image to stdout; the export reports its own progress
        with atomic_path(out_path) as tmp, contextlib.redirect_stdout(io.StringIO()):
            quantize_static(
                str(pre),
                str(tmp),
                _Images(calibration),
                quant_format=_FORMATS[quant_format],
                per_channel=per_channel,
                reduce_range=reduce_range,
                activation_type=act_type,
                weight_type=weight_type,
                op_types_to_quantize=["Conv", "Relu", "Add"],
                nodes_to_quantize=_with_followers(model, conv_nodes_to_quantize(model, float_convs, float_lead))
                if float_tail
                else None,
                calibrate_method=_CALIBRATIONS[method],
                extra_options={
                    "ActivationSymmetric": False,
                    "WeightSymmetric": weight_type == QuantType.QInt8,
                    "CalibPercentile": percentile,
                    "CalibStridedMinMax": CALIBRATION_STRIDE,
                },
            )
    return out_path


def _with_followers(model: onnx.ModelProto, convs: list[str]) -> list[str]:
    """The chosen convolutions plus the Relu/Add nodes between them, so activations stay INT8 end to end.

    Convolutions before the first of ``convs``, and the ReLUs right after them, stay float; so do the nodes fed by
    the first convolution after it that ``convs`` leaves out (and everything after that).
    """
    keep = set(convs)
    all_convs = [n for n in model.graph.node if n.op_type == "Conv"]
    if not keep:
        raise ValueError("no convolution left to quantize: the float leading and trailing ones cover them all")
    lead = all_convs[: next(i for i, n in enumerate(all_convs) if n.name in keep)]
    first_float = next(n for n in all_convs[len(lead) :] if n.name not in keep)
    tail_tensors = set(first_float.output)
    lead_tensors = {t for n in lead for t in n.output}  # float leading layers and the ReLUs right after them
    names = []
    for n in model.graph.node:
        if any(i in tail_tensors for i in n.input):
            tail_tensors.update(n.output)
            continue
        if n.op_type == "Relu" and any(i in lead_tensors for i in n.input):
            lead_tensors.update(n.output)
            continue
        if n.name in keep or n.op_type in ("Relu", "Add"):
            names.append(n.name)
    return names
