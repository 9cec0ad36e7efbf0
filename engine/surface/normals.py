"""Stage: area-weighted unit vertex normals for the exports (on the device)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt


def normals_device(pos: Any, faces: Any, inc: Any = None) -> Any:
    """Unit vertex normals of a device mesh (``wp.array(dtype=wp.vec3)``, (z, y, x), outward), each a sum over the
    vertex's star in a fixed order. ``inc``: the mesh's ``devmesh.Incidence`` if already built."""
    import warp as wp

    from engine.surface.devmesh import Incidence
    from engine.surface.kernels import smoothing as ksmooth

    with wp.ScopedDevice(pos.device):
        if inc is None:
            inc = Incidence(len(pos)).build(faces, len(faces))
        out = wp.empty(len(pos), dtype=wp.vec3)
        wp.launch(ksmooth.star_normals_kernel, dim=len(pos), inputs=[pos, faces, *inc.inputs, out])
    return out


def vertex_normals(
    verts: npt.NDArray[np.float32], faces: npt.NDArray[np.int32], device: Any
) -> npt.NDArray[np.float32]:
    """(V, 3) float32 unit normals in (z, y, x) order, pointing outward (toward values below the level)."""
    import warp as wp

    if len(faces) == 0:
        return np.zeros_like(verts)
    with wp.ScopedDevice(device):
        n = normals_device(wp.array(verts, dtype=wp.vec3), wp.array(faces, dtype=wp.vec3i))
        return n.numpy().astype(np.float32)  # sync point
