"""A probe of the decimation kernels for tests and diagnosis: one pricing pass on a small mesh (``price_edges``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.decimation.passes import MAX_NORMAL_TURN_DEG
from engine.decimation.phases import HIST_BINS, vertex_quadrics
from engine.surface.meshcheck import validate_mesh


def price_edges(
    verts: npt.NDArray[Any],
    faces: npt.NDArray[Any],
    *,
    max_normal_turn_deg: float = MAX_NORMAL_TURN_DEG,
    device: Any = "cpu",
) -> tuple[dict[tuple[int, int], int], int]:
    """One pricing pass of the kernels on a small mesh: ``({(a, b): cost code}, NO_KEY)`` for every edge (a < b),
    the code being ``NO_KEY`` where a guard refuses the collapse; on ``device``'s backend (a Warp device or spec,
    ``"opencl[:N]"``, or a ``Backend``). For tests and diagnosis."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.backend.select import get_backend
    from engine.decimation import kernel_specs as K

    verts, faces = validate_mesh(verts, faces)
    be = get_backend(device)
    pos = be.from_host(np.asarray(verts, np.float32), VEC3F)
    f = be.from_host(np.asarray(faces, np.int32), VEC3I)
    inc, state, origin, quad = vertex_quadrics(pos, f)
    n = 3 * len(faces)
    key, target = be.empty(n, np.int32), be.empty(n, VEC3F)
    checked, cand, listing = be.empty(n, np.int32), be.empty(n, np.int32), be.empty(n, np.int32)
    cos_max = be.scalar(math.cos(math.radians(max_normal_turn_deg)), np.float64)
    dirty, n_listed = be.full(len(verts), 1, np.int32), be.zeros(1, np.int32)
    be.launch(K.EDGE_COSTS, n, [pos, f, inc.count, state, quad, origin, dirty, key, target, checked])
    top, zero = HIST_BINS, be.scalar(0, np.int64)  # every priced edge competes, so every one is checked
    be.launch(K.SELECT_CANDIDATES, n, [key, top, zero, cand, listing, n_listed])
    guards = [listing, n_listed, cand, pos, f, *inc.inputs, state, quad, origin, cos_max, top, zero]
    be.launch(K.CHECK_CANDIDATES, n, [*guards, key, target, checked])
    codes = be.to_host(key)  # sync point
    out: dict[tuple[int, int], int] = {}
    for h, c in enumerate(codes):
        a, b = int(faces[h // 3][h % 3]), int(faces[h // 3][(h % 3 + 1) % 3])
        e = (min(a, b), max(a, b))
        out[e] = min(out.get(e, K.NO_KEY), int(c))
    return out, K.NO_KEY
