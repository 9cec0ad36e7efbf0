"""Stage: area-weighted unit vertex normals for the exports (on the device, any ``engine.backend``)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt


def normals_device(pos: Any, faces: Any, inc: Any = None) -> Any:
    """Unit vertex normals of a device mesh (packed (z, y, x) float triples, outward), each a sum over the vertex's
    star in a fixed order, on the mesh's backend. ``inc``: the mesh's ``devmesh.Incidence`` if already built."""
    from engine.backend.base import VEC3F
    from engine.surface import kernel_specs as k
    from engine.surface.devmesh import Incidence
    from engine.surface.ops import backend_of

    bk = backend_of(pos)
    if inc is None:
        inc = Incidence(len(pos)).build(faces, len(faces))
    out = bk.empty(len(pos), VEC3F)
    bk.launch(k.STAR_NORMALS, len(pos), [pos, faces, *inc.inputs, out])
    return out


def vertex_normals(
    verts: npt.NDArray[np.float32], faces: npt.NDArray[np.int32], device: Any
) -> npt.NDArray[np.float32]:
    """(V, 3) float32 unit normals in (z, y, x) order, pointing outward (toward values below the level).
    ``device``: a Warp device, a device spec ("cpu", "cuda:N", "opencl[:N]") or an ``engine.backend.Backend``."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.surface.ops import get_backend

    if len(faces) == 0:
        return np.zeros_like(verts)
    bk = get_backend(device)
    n = normals_device(bk.from_host(verts, VEC3F), bk.from_host(faces, VEC3I))
    return bk.to_host(n).astype(np.float32)  # sync point
