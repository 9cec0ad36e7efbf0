"""Warp kernels that lay the finished mesh out for its files, on the device where it already is: the patient frame
(``engine.orient``), the STL's facet records and the glTF buffers (``engine.export.glb``'s axes and units).

Arithmetic is float64 where the host exporters use float64, so the files match theirs: positions are mapped in
float64 and stored as float32; the STL facet normal is taken in float32 from the float32 corners, as
``engine.export.stl`` does.
"""

from __future__ import annotations

import warp as wp


@wp.func
def xyz64(p: wp.vec3) -> wp.vec3d:
    """A (z, y, x) float32 position as (x, y, z) float64."""
    return wp.vec3d(wp.float64(p[2]), wp.float64(p[1]), wp.float64(p[0]))


@wp.func
def zyx32(x: wp.vec3d) -> wp.vec3:
    """An (x, y, z) float64 vector as (z, y, x) float32."""
    return wp.vec3(wp.float32(x[2]), wp.float32(x[1]), wp.float32(x[0]))


@wp.kernel
def affine_points(pos: wp.array(dtype=wp.vec3), m: wp.mat33d, offset: wp.vec3d, out: wp.array(dtype=wp.vec3)):
    """``out = m @ p + offset`` on (x, y, z), for (z, y, x) float32 positions (the grid -> patient map, or a shift
    with ``m`` the identity)."""
    v = wp.tid()
    out[v] = zyx32(m @ xyz64(pos[v]) + offset)


@wp.kernel
def rotate_vectors(vec: wp.array(dtype=wp.vec3), m: wp.mat33d, out: wp.array(dtype=wp.vec3)):
    """``out = m @ n`` on (x, y, z), for (z, y, x) float32 vectors (normals under the patient map)."""
    v = wp.tid()
    out[v] = zyx32(m @ xyz64(vec[v]))


@wp.kernel
def reverse_faces(faces: wp.array(dtype=wp.vec3i), out: wp.array(dtype=wp.vec3i)):
    """(a, b, c) -> (c, b, a): the winding a mirroring map needs to keep the faces outward."""
    f = wp.tid()
    t = faces[f]
    out[f] = wp.vec3i(t[2], t[1], t[0])


@wp.kernel
def stl_facets(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    out: wp.array2d(dtype=wp.float32),
    zero_area: wp.array(dtype=wp.int32),
):
    """Per face, the 12 floats of its STL record: the unit normal, then the corners, all in (x, y, z) order (a zero
    normal for a zero-area face); and the count of faces whose corners span exactly zero area in float64."""
    f = wp.tid()
    t = faces[f]
    pa = pos[t[0]]
    pb = pos[t[1]]
    pc = pos[t[2]]
    a = wp.vec3(pa[2], pa[1], pa[0])
    b = wp.vec3(pb[2], pb[1], pb[0])
    c = wp.vec3(pc[2], pc[1], pc[0])
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    if length > 0.0:
        n = n / length
    else:
        n = wp.vec3(0.0)
    for k in range(3):
        out[f, k] = n[k]
        out[f, 3 + k] = a[k]
        out[f, 6 + k] = b[k]
        out[f, 9 + k] = c[k]
    a64 = xyz64(pa)
    n64 = wp.cross(xyz64(pb) - a64, xyz64(pc) - a64)
    if n64[0] == wp.float64(0.0) and n64[1] == wp.float64(0.0) and n64[2] == wp.float64(0.0):
        wp.atomic_add(zero_area, 0, 1)


@wp.kernel
def gltf_vertices(
    pos: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    scale: wp.float64,
    out_pos: wp.array(dtype=wp.vec3),
    out_normals: wp.array(dtype=wp.vec3),
):
    """glTF POSITION and NORMAL from (z, y, x) patient mm: (X, Y, Z) = (x, z, -y), positions times ``scale``
    (mm -> m); normals made unit, +Y where a normal has no direction (glTF requires unit normals)."""
    v = wp.tid()
    p = xyz64(pos[v])
    out_pos[v] = wp.vec3(wp.float32(p[0] * scale), wp.float32(p[2] * scale), wp.float32(-p[1] * scale))
    n = xyz64(normals[v])
    g = wp.vec3d(n[0], n[2], -n[1])
    length = wp.length(g)
    if length > wp.float64(0.0) and wp.isfinite(length):
        g = g / length
    else:
        g = wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
    out_normals[v] = wp.vec3(wp.float32(g[0]), wp.float32(g[1]), wp.float32(g[2]))
