"""Stage: 3x3x3 Gaussian smoothing of the volume on the device (separable, replicated borders), on any backend
(``engine.backend``: the Warp kernel of ``kernels/gaussian.py`` or the OpenCL C of ``kernels/gaussian.cl``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from engine.backend.base import Kernel
from engine.params import GaussianParams

GAUSS3_AXIS = Kernel(
    "gaussian.axis",
    warp="engine.volume.kernels.gaussian:gauss3_axis_kernel",
    opencl="engine.volume.kernels:gaussian.cl:gauss3_axis",
)
_SAMPLE_TYPES = (np.uint8, np.uint16, np.int16, np.float32)


def gaussian_weights(sigma_voxels: float) -> tuple[float, float]:
    """(side, centre) weights of the normalised 3-tap Gaussian."""
    side = math.exp(-1.0 / (2.0 * sigma_voxels * sigma_voxels))
    total = 1.0 + 2.0 * side
    return side / total, 1.0 / total


def sample_dtype(field: Any) -> np.dtype[Any]:
    """The numpy sample type of a device volume (a ``wp.array3d`` or an OpenCL ``CLArray``)."""
    dt = field.dtype
    if isinstance(dt, np.dtype):
        return dt
    import warp as wp

    out: np.dtype[Any] = np.dtype(wp.dtype_to_numpy(dt))
    return out


def smooth_volume(field: Any, params: GaussianParams) -> Any:
    """Smooth a device volume with a 3x3x3 Gaussian, on the backend the field lives on.

    Args:
        field: a (z, y, x) device volume of uint8, uint16, int16 or float32 (``wp.array3d`` on any Warp device, or
            an ``engine.backend`` OpenCL array).
        params: the Gaussian's sigma in voxels.

    Returns:
        A new float32 device volume on the same backend (bit for bit the same values on every backend).
    """
    from engine.backend.select import backend_of

    be = backend_of(field)
    dtype = sample_dtype(field)
    if dtype.type not in _SAMPLE_TYPES:
        raise ValueError(f"Expected a volume of uint8, uint16, int16 or float32, got {dtype}")
    side, centre = gaussian_weights(params.sigma_voxels)
    shape = tuple(field.shape)
    a = be.empty(shape, np.float32)
    b = be.empty(shape, np.float32)
    be.launch(GAUSS3_AXIS, shape, [field, a, 0, side, centre, *shape], dtype=dtype)
    be.launch(GAUSS3_AXIS, shape, [a, b, 1, side, centre, *shape], dtype=np.float32)
    be.launch(GAUSS3_AXIS, shape, [b, a, 2, side, centre, *shape], dtype=np.float32)
    return a
