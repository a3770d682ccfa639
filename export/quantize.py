"""Static INT8 quantization of the SCR graph with onnxruntime: QDQ, per-channel weights, U8S8.

U8S8 (uint8 activations, int8 weights) in QDQ form is what onnxruntime's x86 kernels run fastest;
S8S8 QOperator was measured slower. The head's tail after its last convolution (homogeneous
division, clamp, mean offset) stays in float: quantizing metric coordinates to 8 bits would cost
centimetres by itself.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Iterable

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

from .onnx_graph import INPUT_NAME


class _Images(CalibrationDataReader):
    """Feeds grayscale uint8 images (H, W) as the graph's float input, one at a time."""

    def __init__(self, images: Iterable[np.ndarray]) -> None:
        self._it = iter(images)

    def get_next(self) -> dict[str, np.ndarray] | None:
        img = next(self._it, None)
        if img is None:
            return None
        return {INPUT_NAME: np.ascontiguousarray(img, dtype=np.float32)[None, None]}


def conv_nodes_to_quantize(model: onnx.ModelProto) -> list[str]:
    """Every Conv except the last one (the head's output layer, whose result is divided into metres)."""
    convs = [n.name for n in model.graph.node if n.op_type == "Conv"]
    return convs[:-1]


def quantize_int8(
    fp32_path: str | Path,
    out_path: str | Path,
    calibration: list[np.ndarray],
    method: CalibrationMethod = CalibrationMethod.MinMax,
    float_tail: bool = True,
) -> Path:
    """Quantize the FP32 model at ``fp32_path`` using ``calibration`` grayscale images (H, W) uint8.

    ``float_tail=False`` quantizes the last convolution too (measured against in bench/bench_export.py).
    """
    if not calibration:
        raise ValueError("INT8 calibration needs at least one image")
    out_path = Path(out_path)
    with tempfile.TemporaryDirectory() as td:
        pre = Path(td) / "pre.onnx"
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        model = onnx.load(str(pre))
        nodes = conv_nodes_to_quantize(model) if float_tail else [n.name for n in model.graph.node if n.op_type == "Conv"]
        with atomic_path(out_path) as tmp:
            quantize_static(
                str(pre), str(tmp), _Images(calibration),
                quant_format=QuantFormat.QDQ, per_channel=True,
                activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                op_types_to_quantize=["Conv", "Relu", "Add"],
                nodes_to_quantize=_with_followers(model, nodes) if float_tail else None,
                calibrate_method=method,
                extra_options={"ActivationSymmetric": False, "WeightSymmetric": True},
            )
    return out_path


def _with_followers(model: onnx.ModelProto, convs: list[str]) -> list[str]:
    """The chosen convolutions plus the Relu/Add nodes between them, so activations stay INT8 end to end.

    Nodes fed by the excluded last convolution stay float.
    """
    keep = set(convs)
    last_conv = [n for n in model.graph.node if n.op_type == "Conv"][-1]
    tail_tensors = set(last_conv.output)
    names = []
    for n in model.graph.node:
        if any(i in tail_tensors for i in n.input):
            tail_tensors.update(n.output)
            continue
        if n.name in keep or (n.op_type in ("Relu", "Add") and n is not last_conv):
            names.append(n.name)
    return names
