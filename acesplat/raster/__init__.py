"""Torch-free differentiable Gaussian rasterizer (numba kernels, numpy interface).

Public API in :mod:`.rasterizer`; the kernels live in ``_project_kernels`` (per Gaussian) and
``_tile_kernels`` (per tile), sharing the record layout in ``_layout``; ``_threads`` runs them
over chunks on a thread pool.
"""

from acesplat.raster._threads import get_num_threads, set_num_threads
from acesplat.raster.rasterizer import (
    ALPHA_MAX,
    ALPHA_MIN,
    DILATION,
    FRUSTUM_SLACK,
    MAHA2_MAX,
    T_MIN,
    TILE,
    RasterContext,
    RasterGradients,
    RenderResult,
    ndc_grad_norm,
    rasterize,
    rasterize_backward,
)

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "DILATION",
    "FRUSTUM_SLACK",
    "MAHA2_MAX",
    "T_MIN",
    "TILE",
    "RasterContext",
    "RasterGradients",
    "RenderResult",
    "ndc_grad_norm",
    "rasterize",
    "rasterize_backward",
    "get_num_threads",
    "set_num_threads",
]
