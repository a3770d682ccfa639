"""Stage 2: Gaussian splatting trained on the CPU (torch). Importing this package imports torch.

The differentiable renderer is :func:`render` (numba kernels from acesplat.raster behind a
torch.autograd.Function).
"""

from acesplat.splat.raster_torch import RenderOutput, render, screen_grad_norm

__all__ = ["RenderOutput", "render", "screen_grad_norm"]
