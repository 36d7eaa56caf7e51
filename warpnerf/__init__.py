"""warpnerf: grid-encoded NeRFs with NVIDIA Warp kernels and G²fR frequency regularization.

Importing the package is cheap and never touches CUDA: Warp is initialised lazily by the
first op that needs it (see :mod:`warpnerf.device`).
"""

__version__ = "0.1.0"
