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
    the code being ``NO_KEY`` where a guard refuses the collapse. For tests and diagnosis."""
    import warp as wp

    from engine.decimation.kernels import costs as kcost
    from engine.decimation.kernels import guards as kguard
    from engine.device import resolve_device

    verts, faces = validate_mesh(verts, faces)
    with wp.ScopedDevice(resolve_device(device)):
        pos = wp.array(np.asarray(verts, np.float32), dtype=wp.vec3)
        f = wp.array(np.asarray(faces, np.int32), dtype=wp.vec3i)
        inc, state, origin, quad = vertex_quadrics(pos, f)
        key = wp.empty(3 * len(faces), dtype=wp.int32)
        target = wp.empty(3 * len(faces), dtype=wp.vec3)
        cos_max = wp.float64(math.cos(math.radians(max_normal_turn_deg)))
        dirty = wp.ones(len(verts), dtype=wp.int32)
        checked = wp.empty(len(key), dtype=wp.int32)
        cand = wp.empty(len(key), dtype=wp.int32)
        wp.launch(
            kcost.edge_costs, dim=len(key), inputs=[pos, f, inc.count, state, quad, origin, dirty, key, target, checked]
        )
        top = HIST_BINS  # every priced edge competes, so every one is checked
        listing = wp.empty(len(key), dtype=wp.int32)
        n_listed = wp.zeros(1, dtype=wp.int32)
        wp.launch(kcost.select_candidates, dim=len(key), inputs=[key, top, wp.int64(0), cand, listing, n_listed])
        wp.launch(
            kguard.check_candidates,
            dim=len(key),
            inputs=[listing, n_listed, cand, pos, f, *inc.inputs, state, quad, origin, cos_max, top, wp.int64(0)],
            outputs=[key, target, checked],
        )
        codes = key.numpy()
    out: dict[tuple[int, int], int] = {}
    for h, c in enumerate(codes):
        a, b = int(faces[h // 3][h % 3]), int(faces[h // 3][(h % 3 + 1) % 3])
        e = (min(a, b), max(a, b))
        out[e] = min(out.get(e, int(kcost.NO_KEY)), int(c))
    return out, int(kcost.NO_KEY)
