"""acesplat: ACEsplat scene coordinate regression and Gaussian splatting, from desktop to edge.

Importing this package imports neither torch nor onnx: the torch-free primitives live in
``acesplat.core``; the desktop training code (``acesplat.scr``) imports torch itself.
"""

__version__ = "0.1.0"
