"""Torch-free alignment of a pose against posed mapping images (warp, dense flow, PnP) and the keyframes it uses."""
