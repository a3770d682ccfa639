"""Column layout of the per-Gaussian screen-space record shared by the projection and tile kernels.

One row of 16 values (64 bytes in float32: one cache line) holds everything compositing reads for a
Gaussian, so the tile loop touches one line per Gaussian instead of gathering from ten arrays.

Numba's on-disk cache is keyed on the file that defines a kernel, not on the globals it freezes: after
editing a constant here, delete ``acesplat/core/raster/__pycache__`` so the kernels recompile.
"""

REC_WIDTH = 16
MX, MY = 0, 1  # projected mean, pixels (pixel centres at integer coordinates)
CA, CB, CC = 2, 3, 4  # conic = inverse 2D covariance [[CA, CB], [CB, CC]]
OPAC = 5  # sigmoid(opacity logit)
RED, GREEN, BLUE = 6, 7, 8  # activated colour, clamped at 0
DEPTH = 9  # camera z
POWER_MIN = 10  # a pixel contributes iff exponent >= POWER_MIN (3-sigma and alpha >= 1/255 cut)
MAHA2 = 11  # the same bound as a squared Mahalanobis distance (= -2 * POWER_MIN)
EXT_X, EXT_Y = 12, 13  # half-extent of that ellipse along x and y, pixels

# The 10 per-slot gradient channels the tile backward writes and the projection backward reads.
GRAD_WIDTH = 10
G_MX, G_MY, G_CA, G_CB, G_CC, G_RED, G_GREEN, G_BLUE, G_OPAC, G_DEPTH = range(10)
