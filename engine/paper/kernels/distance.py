"""Warp kernels of the surface distance (host side: ``engine.paper.metrics.SurfaceQuery``)."""

from __future__ import annotations

import warp as wp


@wp.kernel
def closest_distance_kernel(
    mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float, out: wp.array(dtype=float)
):
    """Per point, the distance to the closest point of the mesh (a BVH query), or -1 where none is within
    ``max_dist``."""
    tid = wp.tid()
    p = points[tid]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if q.result:
        out[tid] = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - p)
    else:
        out[tid] = -1.0
