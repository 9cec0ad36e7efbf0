"""Stage: surface-preserving Laplacian smoothing on the device (the paper's step 4).

Each iteration moves every vertex toward the mean of its neighbours, but only if none of its faces turns by
``angle_deg`` or more (checked with its neighbours held still, then re-checked after all moves: a face that
turned too far sends its vertices back). Boundary vertices of open meshes stay fixed. With the default 0.5
degrees only nearly flat regions move, so features and volume are kept.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.params import SmoothParams


def unique_edges(faces: npt.NDArray[np.int32]) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.bool_]]:
    """Undirected edges (E, 2) and, per edge, whether it lies on the boundary (in one face only) (numpy)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1).astype(np.int64)
    key = e[:, 0] * (int(faces.max()) + 1) + e[:, 1]
    _, first, counts = np.unique(key, return_index=True, return_counts=True)
    return e[first].astype(np.int32), counts == 1


def smooth_device(pos: Any, faces: Any, params: SmoothParams, inc: Any = None) -> tuple[Any, dict[str, Any]]:
    """Smooth a device mesh in place (``pos`` ``wp.array(dtype=wp.vec3)``, ``faces`` ``wp.array(dtype=wp.vec3i)``);
    returns ``pos`` and a summary (moves per iteration). Only vertices with one closed fan of faces move (border
    and non-manifold vertices stay). ``inc``: the mesh's ``devmesh.Incidence`` if already built."""
    import warp as wp

    from engine.surface.devmesh import Incidence, vertex_classes
    from engine.surface.kernels import smoothing as ksmooth

    n = len(pos)
    if len(faces) == 0 or n == 0:
        return pos, {"moved_per_iteration": []}
    cos_max = math.cos(math.radians(params.angle_deg))
    with wp.ScopedDevice(pos.device):
        if inc is None:
            inc = Incidence(n).build(faces, len(faces))
        fixed = wp.empty(n, dtype=wp.int32)
        wp.launch(ksmooth.fixed_from_classes, dim=n, inputs=[vertex_classes(faces, inc), fixed])
        new = wp.empty(n, dtype=wp.vec3)  # the candidates, then the moved positions (``pos`` keeps the old ones)
        flag = wp.empty(n, dtype=wp.int32)
        counter = wp.zeros(1, dtype=wp.int32)
        viol = wp.zeros(1, dtype=wp.int32)
        moved: list[int] = []
        for _ in range(params.iterations):
            flag.zero_()
            counter.zero_()
            wp.launch(ksmooth.star_neighbour_mean_kernel, dim=n, inputs=[pos, faces, *inc.inputs, new])
            wp.launch(ksmooth.reject_kernel, dim=len(faces), inputs=[pos, new, faces, cos_max, flag])
            wp.launch(ksmooth.accept_kernel, dim=n, inputs=[pos, new, flag, fixed, counter])
            flag.zero_()
            for _pass in range(50):
                viol.zero_()
                wp.launch(ksmooth.violation_kernel, dim=len(faces), inputs=[pos, new, faces, cos_max, flag, viol])
                if int(viol.numpy()[0]) == 0:  # sync point
                    break
                wp.launch(ksmooth.revert_kernel, dim=n, inputs=[pos, new, flag])
            wp.copy(pos, new)
            moved.append(int(counter.numpy()[0]))  # sync point
    return pos, {"moved_per_iteration": moved}


def smooth_mesh(
    verts: npt.NDArray[np.float32], faces: npt.NDArray[np.int32], params: SmoothParams, device: Any
) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
    """Smooth a mesh; returns new vertices (same order) and a summary (moves per iteration).

    Args:
        verts: (V, 3) float32 (z, y, x) mm.
        faces: (F, 3) int32.
        params: iterations and angle threshold.
        device: a Warp device.
    """
    import warp as wp

    if len(faces) == 0:
        return verts.copy(), {"moved_per_iteration": []}
    with wp.ScopedDevice(device):
        pos, info = smooth_device(wp.array(verts, dtype=wp.vec3), wp.array(faces, dtype=wp.vec3i), params)
        return pos.numpy().astype(np.float32), info  # sync point
