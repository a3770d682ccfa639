"""SCR network -> one ONNX graph: grayscale image (1, 1, H, W) in [0, 255] in; coordinates (1, 3, H/s, W/s) and the
encoder's features (1, C, H/s, W/s) out, s the output stride (8, or 4 for a dense bundle). H and W are dynamic
(any multiple of 8): the bundle's input size is the one it was checked at, and the edge may run the same graph
smaller where a later stage recovers the precision (acesplat.align.keyframe_align.PreciseSettings).

Normalisation and the mean offset live inside the network, so the graph needs nothing but pixels. The
features are the head's input, a second output at no extra compute: the edge's splat initializer takes
them instead of running the encoder again (export/splat_export.py).
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import torch
from torch.export import Dim

from acesplat.core.atomic import atomic_path
from acesplat.core.bundle import SCR_COORDS_OUTPUT, SCR_FEATURES_OUTPUT
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.scr.network import SCRNetwork, normalize_gray

INPUT_NAME = "gray"
OUTPUT_NAME = SCR_COORDS_OUTPUT
FEATURES_NAME = SCR_FEATURES_OUTPUT
OPSET = 18
"""Opset 18: supported by onnxruntime >= 1.14 and by the dynamo exporter without down-conversion."""


class ScrWithFeatures(torch.nn.Module):
    """``net`` returning (coordinates, encoder features): the graph the bundle ships."""

    def __init__(self, net: SCRNetwork, output_stride: int = OUTPUT_STRIDE) -> None:
        super().__init__()
        self.net = net
        self.output_stride = output_stride

    def forward(self, gray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        feats = self.net.encoder(normalize_gray(gray), self.output_stride)
        return self.net.head(feats), feats


def export_scr_onnx(
    net: SCRNetwork,
    size_hw: tuple[int, int],
    out_path: str | Path,
    output_stride: int = OUTPUT_STRIDE,
    dynamic: bool = True,
) -> Path:
    """Write ``net`` traced at the input size ``size_hw`` (H, W) and ``output_stride`` to ``out_path`` as a
    single-file ONNX model; ``dynamic``: H and W are symbolic multiples of 8 (else fixed at ``size_hw``)."""
    h, w = size_hw
    if h % 8 or w % 8:
        raise ValueError(f"input size must be a multiple of 8 in both sides, got {h}x{w}")
    model = ScrWithFeatures(net, output_stride).eval()
    example = torch.full((1, 1, h, w), 128.0)
    out_path = Path(out_path)
    with atomic_path(out_path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logging.getLogger("torch.onnx").setLevel(logging.ERROR)
        torch.onnx.export(
            model,
            (example,),
            str(tmp),
            dynamo=True,
            external_data=False,
            opset_version=OPSET,
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME, FEATURES_NAME],
            dynamic_shapes={"gray": {2: 8 * Dim("rows8", min=1), 3: 8 * Dim("cols8", min=1)}} if dynamic else None,
            verbose=False,
        )
    return out_path
