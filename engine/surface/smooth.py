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
    """Smooth a device mesh in place (packed (z, y, x) positions and faces on one ``engine.backend``); returns
    ``pos`` and a summary (moves per iteration). Only vertices with one closed fan of faces move (border and
    non-manifold vertices stay). ``inc``: the mesh's ``devmesh.Incidence`` if already built."""
    from engine.backend.base import VEC3F
    from engine.surface import kernel_specs as k
    from engine.surface.devmesh import Incidence, vertex_classes
    from engine.surface.ops import backend_of

    n, nf = len(pos), len(faces)
    if nf == 0 or n == 0:
        return pos, {"moved_per_iteration": []}
    bk = backend_of(pos)
    cos_max = math.cos(math.radians(params.angle_deg))
    if inc is None:
        inc = Incidence(n).build(faces, nf)
    fixed = bk.empty(n, np.int32)
    bk.launch(k.FIXED, n, [vertex_classes(faces, inc), fixed])
    new = bk.empty(n, VEC3F)  # the candidates, then the moved positions (``pos`` keeps the old ones)
    flag = bk.empty(n, np.int32)
    counter = bk.zeros(1, np.int32)
    viol = bk.zeros(1, np.int32)
    moved: list[int] = []
    for _ in range(params.iterations):
        bk.fill(flag, 0)
        bk.fill(counter, 0)
        bk.launch(k.NEIGHBOUR_MEAN, n, [pos, faces, *inc.inputs, new])
        bk.launch(k.REJECT, nf, [pos, new, faces, cos_max, flag])
        bk.launch(k.ACCEPT, n, [pos, new, flag, fixed, counter])
        bk.fill(flag, 0)
        for _pass in range(50):
            bk.fill(viol, 0)
            bk.launch(k.VIOLATIONS, nf, [pos, new, faces, cos_max, flag, viol])
            if int(bk.to_host(viol)[0]) == 0:  # sync point
                break
            bk.launch(k.REVERT, n, [pos, new, flag])
        bk.copy(pos, new)
        moved.append(int(bk.to_host(counter)[0]))  # sync point
    return pos, {"moved_per_iteration": moved}


def smooth_mesh(
    verts: npt.NDArray[np.float32], faces: npt.NDArray[np.int32], params: SmoothParams, device: Any
) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
    """Smooth a mesh; returns new vertices (same order) and a summary (moves per iteration).

    Args:
        verts: (V, 3) float32 (z, y, x) mm.
        faces: (F, 3) int32.
        params: iterations and angle threshold.
        device: a Warp device, a device spec ("cpu", "cuda:N", "opencl[:N]") or an ``engine.backend.Backend``.
    """
    from engine.backend.base import VEC3F, VEC3I
    from engine.surface.ops import get_backend

    if len(faces) == 0:
        return verts.copy(), {"moved_per_iteration": []}
    bk = get_backend(device)
    pos, info = smooth_device(bk.from_host(verts, VEC3F), bk.from_host(faces, VEC3I), params)
    return bk.to_host(pos).astype(np.float32), info  # sync point
