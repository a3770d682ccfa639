"""The Gaussian models a bundle may carry, torch-free: the roles and file names export/splat_export.py writes and
edge/refine/bundle_models.py reads, and the initializer graph's input and output names."""

from __future__ import annotations

ROLE_GAUSSIANS = "gaussians"
"""The scene's 3DGS PLY."""
ROLE_SPLAT_INIT = "splat_init_fp32"
"""The Gaussian initializer: feature adapter + init head in one ONNX graph, fed the SCR graph's features."""
GAUSSIANS_FILE = "gaussians.ply"
INIT_FILE = "splat_init.onnx"
INIT_INPUTS = ("features", "prior")
"""The initializer's inputs: the SCR graph's features (1, C, H/8, W/8) and the head's prior (1, 7, H, W)."""
INIT_OUTPUT = "raw"
