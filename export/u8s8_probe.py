"""The U8S8 saturation probe the edge ships (edge/u8s8_probe.onnx): the same integer product twice, uint8 x int8
(``Y``) and uint8 x uint8 (``Y_exact``), with values large enough that every adjacent pair of products overflows
int16.

onnxruntime's x86 kernel for U8S8 on CPUs without VNNI sums such pairs with a saturating instruction (vpmaddubsw);
VNNI, AMX and the widening U8U8 kernels are exact. The edge feeds 255 everywhere and compares the two outputs before
it trusts a U8S8 INT8 graph (edge.int8_check.u8s8_probe_error).

    python -P -m export.u8s8_probe edge/u8s8_probe.onnx     # (re)writes the shipped file
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

PROBE_SHAPE = (8, 64, 16)
"""(rows, inner, columns) of the product: big enough for onnxruntime's blocked kernel, not more."""
PROBE_SEED = 0
"""Seed of the operands, so the file is reproducible."""


PROBE_INPUT = 255
"""The value the edge feeds in every element of ``A``: with weights of at least 100, a pair sum of products is at
least 51,000, past int16's 32,767."""


def probe_weights() -> np.ndarray:
    """B (inner, columns) int8 in [100, 127]."""
    _, k, n = PROBE_SHAPE
    return np.random.default_rng(PROBE_SEED).integers(100, 128, size=(k, n), dtype=np.int8)


def probe_model() -> onnx.ModelProto:
    """The probe graph: input ``A`` (rows, inner) uint8; outputs ``Y`` = A @ B with B int8 and ``Y_exact`` = A @ B
    with the same values as uint8 (both int32)."""
    m, k, n = PROBE_SHAPE
    b = probe_weights()
    graph = helper.make_graph(
        [
            helper.make_node("MatMulInteger", ["A", "B"], ["Y"]),
            helper.make_node("MatMulInteger", ["A", "B_u8"], ["Y_exact"]),
        ],
        "u8s8_probe",
        [helper.make_tensor_value_info("A", TensorProto.UINT8, [m, k])],
        [
            helper.make_tensor_value_info("Y", TensorProto.INT32, [m, n]),
            helper.make_tensor_value_info("Y_exact", TensorProto.INT32, [m, n]),
        ],
        [numpy_helper.from_array(b, "B"), numpy_helper.from_array(b.astype(np.uint8), "B_u8")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], producer_name="acesplat")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def main(argv: list[str]) -> None:
    if len(argv) != 1:
        sys.exit("usage: python -P -m export.u8s8_probe OUT.onnx")
    Path(argv[0]).write_bytes(probe_model().SerializeToString())


if __name__ == "__main__":
    main(sys.argv[1:])
