"""The volume stages of the paper (before the isosurface): the optional per-slice preprocessing and crop
(``preprocess``, host), the body mask that keeps the bone of the body only (``bodymask``, host), and the 3x3x3
Gaussian (``gaussian``, device, on any ``engine.backend``; kernels in ``engine.volume.kernels``: Warp and OpenCL C).

Public names load lazily (``engine._lazy``): importing this package imports neither its modules nor Warp.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.volume.bodymask import body_outline, isolate_bone
    from engine.volume.gaussian import gaussian_weights, smooth_volume
    from engine.volume.preprocess import crop_volume, preprocess_volume

__all__ = [
    "body_outline",
    "crop_volume",
    "gaussian_weights",
    "isolate_bone",
    "preprocess_volume",
    "smooth_volume",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "body_outline": ".bodymask",
        "isolate_bone": ".bodymask",
        "gaussian_weights": ".gaussian",
        "smooth_volume": ".gaussian",
        "crop_volume": ".preprocess",
        "preprocess_volume": ".preprocess",
    },
)
