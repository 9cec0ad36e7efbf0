"""Stage: area-weighted unit vertex normals for the exports (on the device)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt


def vertex_normals(
    verts: npt.NDArray[np.float32], faces: npt.NDArray[np.int32], device: Any
) -> npt.NDArray[np.float32]:
    """(V, 3) float32 unit normals in (z, y, x) order, pointing outward (toward values below the level)."""
    import warp as wp

    from engine.kernels import mesh as km

    if len(faces) == 0:
        return np.zeros_like(verts)
    with wp.ScopedDevice(device):
        pos = wp.array(verts, dtype=wp.vec3)
        acc = wp.zeros(len(verts), dtype=wp.vec3)
        wp.launch(km.vertex_normals_kernel, dim=len(faces), inputs=[pos, wp.array(faces, dtype=wp.vec3i), acc])
        wp.launch(km.normalize_kernel, dim=len(verts), inputs=[acc])
        return acc.numpy().astype(np.float32)  # sync point
