"""Stage: 3x3x3 Gaussian smoothing of the volume on the device (separable, replicated borders)."""

from __future__ import annotations

import math
from typing import Any

from engine.params import GaussianParams


def gaussian_weights(sigma_voxels: float) -> tuple[float, float]:
    """(side, centre) weights of the normalised 3-tap Gaussian."""
    side = math.exp(-1.0 / (2.0 * sigma_voxels * sigma_voxels))
    total = 1.0 + 2.0 * side
    return side / total, 1.0 / total


def smooth_volume(field: Any, params: GaussianParams) -> Any:
    """Smooth a device volume with a 3x3x3 Gaussian.

    Args:
        field: ``wp.array3d`` (z, y, x) of uint8, uint16, int16 or float32 on any device.
        params: the Gaussian's sigma in voxels.

    Returns:
        A new float32 ``wp.array3d`` on the same device.
    """
    import warp as wp

    from engine.volume.kernels.gaussian import gauss3_axis_kernel

    side, centre = gaussian_weights(params.sigma_voxels)
    a = wp.empty(field.shape, dtype=wp.float32, device=field.device)
    b = wp.empty(field.shape, dtype=wp.float32, device=field.device)
    wp.launch(gauss3_axis_kernel, dim=field.shape, inputs=[field, a, 0, side, centre], device=field.device)
    wp.launch(gauss3_axis_kernel, dim=field.shape, inputs=[a, b, 1, side, centre], device=field.device)
    wp.launch(gauss3_axis_kernel, dim=field.shape, inputs=[b, a, 2, side, centre], device=field.device)
    return a
