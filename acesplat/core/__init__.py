"""Torch-free primitives: geometry, cameras, scene layout, poses, PnP, metrics.

The edge runtime and the firmware bridge may import from here; nothing here imports torch or onnx.
"""
