"""Warp types and kernels of the Garland-Heckbert quadrics (host side: ``engine.decimation.phases``).

Quadrics are float64 (10 coefficients), taken about a local origin (the mesh's centre) so that they do not cancel
at scan scale.
"""

from __future__ import annotations

import warp as wp

from engine.backend.kernels.vectors import vec10d

quadric = vec10d  # the backend's VEC10D element


@wp.func
def local(p: wp.vec3, origin: wp.vec3d) -> wp.vec3d:
    return wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2])) - origin


@wp.func
def plane_quadric(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> quadric:
    """Area-weighted quadric of the plane through a, b, c (zero for a degenerate face)."""
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    q = quadric()
    if length > wp.float64(0.0):
        u = n / length
        d = -wp.dot(u, a)
        w = wp.float64(0.5) * length
        q = w * quadric(
            u[0] * u[0], u[0] * u[1], u[0] * u[2], u[0] * d,
            u[1] * u[1], u[1] * u[2], u[1] * d,
            u[2] * u[2], u[2] * d,
            d * d,
        )  # fmt: skip
    return q


@wp.func
def q_eval(q: quadric, p: wp.vec3d) -> wp.float64:
    x = p[0]
    y = p[1]
    z = p[2]
    two = wp.float64(2.0)
    return (
        q[0] * x * x
        + two * q[1] * x * y
        + two * q[2] * x * z
        + two * q[3] * x
        + q[4] * y * y
        + two * q[5] * y * z
        + two * q[6] * y
        + q[7] * z * z
        + two * q[8] * z
        + q[9]
    )


@wp.kernel
def vertex_quadrics(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    origin: wp.vec3d,
    quad: wp.array(dtype=quadric),
):
    v = wp.tid()
    q = quadric()
    lo = offset[v]
    for i in range(count[v]):
        t = faces[star[lo + i]]
        q = q + plane_quadric(local(pos[t[0]], origin), local(pos[t[1]], origin), local(pos[t[2]], origin))
    quad[v] = q


@wp.kernel
def scatter_kept(
    count: wp.array(dtype=wp.int32),
    slot: wp.array(dtype=wp.int32),
    quad: wp.array(dtype=quadric),
    kept: wp.array(dtype=wp.int32),
    out_quad: wp.array(dtype=quadric),
):
    """For a compaction that carries the quadrics: each kept vertex's old index and its quadric."""
    v = wp.tid()
    if count[v] > 0:
        kept[slot[v]] = v
        out_quad[slot[v]] = quad[v]
