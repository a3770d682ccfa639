"""Torch-free splat core shared by Stage 2 and the edge: which SCR cells become Gaussians, and where."""
