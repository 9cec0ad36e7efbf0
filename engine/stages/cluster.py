"""Quadric vertex clustering on the device: the viewing copies' last resort when topology must give way.

A piece of high genus (a trabecular network) cannot be decimated far with the link condition: every tunnel keeps
a ring of faces. To meet a phone's budget anyway, the copy is clustered on a grid (Lindstrom's out-of-core
simplification): one vertex per occupied cell, at the cell's quadric minimum; tunnels narrower than a cell close,
and the copy may lose watertightness. The cell size is searched so that the face count meets the budget as
closely as possible. Never used for the print model.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from engine.stages.devmesh import exclusive_scan

SEARCH_STEPS = 14


def _cells(pos: Any, lo: Any, h: float) -> tuple[Any, Any, Any, int]:
    """Per vertex its cell id, the vertices sorted by cell and each cell's first sorted slot; and the cell count."""
    import warp as wp

    from engine.kernels import cluster as kc

    n = len(pos)
    keys = wp.empty(2 * n, dtype=wp.int64)
    order = wp.empty(2 * n, dtype=wp.int32)
    wp.launch(kc.cell_keys, dim=n, inputs=[pos, lo, 1.0 / h, keys, order])
    wp.utils.radix_sort_pairs(keys, order, n)
    flag = wp.empty(n, dtype=wp.int32)
    wp.launch(kc.run_starts, dim=n, inputs=[keys, flag])
    scan, n_cells = exclusive_scan(flag)
    cell_of = wp.empty(n, dtype=wp.int32)
    start = wp.empty(max(n_cells, 1), dtype=wp.int32)
    wp.launch(kc.assign_cells, dim=n, inputs=[flag, scan, order, cell_of, start])
    return cell_of, order, start, n_cells


def _faces(faces: Any, cell_of: Any) -> tuple[Any, int]:
    """The faces in cells, each set of three cells once (the first face's winding); and their count."""
    import warp as wp

    from engine.kernels import cluster as kc

    nf = len(faces)
    cells = wp.empty(nf, dtype=wp.vec3i)
    keys = wp.empty(2 * nf, dtype=wp.int64)
    order = wp.empty(2 * nf, dtype=wp.int32)
    wp.launch(kc.face_cells, dim=nf, inputs=[faces, cell_of, cells, keys, order])
    wp.utils.radix_sort_pairs(keys, order, nf)
    flag = wp.empty(nf, dtype=wp.int32)
    wp.launch(kc.run_starts, dim=nf, inputs=[keys, flag])
    scan, kept = exclusive_scan(flag)
    out = wp.empty(kept, dtype=wp.vec3i)
    wp.launch(kc.gather_faces, dim=nf, inputs=[flag, scan, order, cells, out])
    return out, kept


def cluster_device(pos: Any, faces: Any, max_triangles: int) -> tuple[Any, Any, dict[str, Any]]:
    """Cluster a device mesh down to at most ``max_triangles`` faces (as close below it as the cell size allows).

    Returns new device arrays (``wp.vec3`` positions, ``wp.vec3i`` faces) and a report: ``cell_mm``, ``faces``.
    """
    import warp as wp

    from engine.kernels import cluster as kc
    from engine.stages.decimate import vertex_quadrics
    from engine.stages.devmesh import bounds, compact_vertices

    t0 = time.perf_counter()
    with wp.ScopedDevice(pos.device):
        lo_np, hi_np = bounds(pos)
        lo = wp.vec3(*(float(x) for x in lo_np))
        diag = float(np.linalg.norm(hi_np - lo_np)) or 1.0
        # the cell size: bisection in log scale between a tiny cell and a quarter of the diagonal
        small, large = diag * 1e-6, diag / 4
        best: float | None = None
        for _ in range(SEARCH_STEPS):
            h = math.sqrt(small * large)
            cell_of, _, _, n_cells = _cells(pos, lo, h)
            if n_cells >= (1 << 21):
                small = h
                continue
            _, kept = _faces(faces, cell_of)
            if kept > max_triangles:
                small = h
            else:
                large, best = h, h
        h = best if best is not None else large
        cell_of, order, start, n_cells = _cells(pos, lo, h)
        out_faces, kept = _faces(faces, cell_of)
        _, _, origin, quad = vertex_quadrics(pos, faces)
        cell_pos = wp.empty(max(n_cells, 1), dtype=wp.vec3)
        wp.launch(kc.cell_positions, dim=n_cells, inputs=[pos, quad, order, start, len(pos), n_cells, origin, cell_pos])
        out_pos, out_faces = compact_vertices(cell_pos[:n_cells], out_faces)
    return out_pos, out_faces, {"cell_mm": h, "faces": kept, "seconds": time.perf_counter() - t0}
