"""Warp kernels that lay the finished mesh out for its files, on the device where it already is: the patient frame
(``engine.orient``), the STL's facet records and the glTF buffers (``engine.export.glb``'s axes and units).

Arithmetic is float64 where the host exporters use float64, so the files match theirs: positions are mapped in
float64 and stored as float32; the STL facet normal is taken in float32 from the float32 corners, as
``engine.export.stl`` does. OpenCL C twins: ``layout.cl`` (``rasterize_nearest``, the preview's: ``preview.cl``).
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


@wp.func
def mapped(m: wp.array(dtype=wp.float64), p: wp.vec3d, shift: wp.float64) -> wp.vec3:
    """``m[:9]`` (a 3 x 3 map, row-major) times ``p``, plus ``shift`` times the offset ``m[9:12]``, on (x, y, z);
    returned (z, y, x) float32 (each row summed left to right, as ``engine.export.kernels.layout.cl``)."""
    r = wp.vec3d()
    for i in range(3):
        s = m[3 * i] * p[0]
        s = s + m[3 * i + 1] * p[1]
        s = s + m[3 * i + 2] * p[2]
        if shift != wp.float64(0.0):
            s = s + m[9 + i]
        r[i] = s
    return zyx32(r)


@wp.kernel
def affine_points(pos: wp.array(dtype=wp.vec3), m: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.vec3)):
    """``out = M @ p + offset`` on (x, y, z), for (z, y, x) float32 positions (the grid -> patient map, or a shift
    with ``M`` the identity); ``m``: M row-major, then the offset (12 values)."""
    v = wp.tid()
    out[v] = mapped(m, xyz64(pos[v]), wp.float64(1.0))


@wp.kernel
def rotate_vectors(vec: wp.array(dtype=wp.vec3), m: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.vec3)):
    """``out = M @ n`` on (x, y, z), for (z, y, x) float32 vectors (normals under the patient map)."""
    v = wp.tid()
    out[v] = mapped(m, xyz64(vec[v]), wp.float64(0.0))


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
    first: int,
    out: wp.array2d(dtype=wp.float32),
    zero_area: wp.array(dtype=wp.int32),
):
    """Per face ``first + f``, into row ``f``: the 12 floats of its STL record: the unit normal, then the corners,
    all in (x, y, z) order (a zero normal for a zero-area face); and the count of faces whose corners span exactly
    zero area in float64."""
    f = wp.tid()
    t = faces[first + f]
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
    scales: wp.array(dtype=wp.float64),
    out_pos: wp.array(dtype=wp.vec3),
    out_normals: wp.array(dtype=wp.vec3),
):
    """glTF POSITION and NORMAL from (z, y, x) patient mm: (X, Y, Z) = (x, z, -y), positions times ``scale``
    (mm -> m, ``scales[0]``); normals made unit, +Y where a normal has no direction (glTF requires unit normals)."""
    v = wp.tid()
    scale = scales[0]
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


DEPTH_STEPS = wp.constant(wp.float32(1073741823.0))  # depth in [0, 1] quantised to 30 bits for the packed key


@wp.kernel
def rasterize_nearest(
    px: wp.array(dtype=wp.float32),
    py: wp.array(dtype=wp.float32),
    depth: wp.array(dtype=wp.float32),
    tris: wp.array(dtype=wp.vec3i),
    n: wp.int32,
    nearest: wp.array(dtype=wp.int64),
):
    """Scan-convert one triangle (image coordinates, y downward; ``depth`` in [0, 1], smaller is nearer) into an
    ``n`` x ``n`` z-buffer: every pixel centre inside the front-facing triangle takes the atomic min of
    ``(depth code << 32) | triangle``, so the nearest triangle wins and ties go to the lower index
    (deterministic, whatever the launch order)."""
    t = wp.tid()
    f = tris[t]
    x0, x1, x2 = px[f[0]], px[f[1]], px[f[2]]
    y0, y1, y2 = py[f[0]], py[f[1]], py[f[2]]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    if not (area < wp.float32(0.0)):  # counter-clockwise in y-up is clockwise in the y-down image: front faces
        return
    bx0 = wp.max(wp.int32(wp.ceil(wp.min(x0, wp.min(x1, x2)) - 0.5)), 0)
    bx1 = wp.min(wp.int32(wp.floor(wp.max(x0, wp.max(x1, x2)) - 0.5)), n - 1)
    by0 = wp.max(wp.int32(wp.ceil(wp.min(y0, wp.min(y1, y2)) - 0.5)), 0)
    by1 = wp.min(wp.int32(wp.floor(wp.max(y0, wp.max(y1, y2)) - 0.5)), n - 1)
    d0, d1, d2 = depth[f[0]], depth[f[1]], depth[f[2]]
    slack = wp.float32(-1.0e-6)  # a sample on a shared edge belongs to both triangles: no pinholes
    for sy in range(by0, by1 + 1):
        cy = wp.float32(sy) + 0.5
        for sx in range(bx0, bx1 + 1):
            cx = wp.float32(sx) + 0.5
            w0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) / area
            w1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) / area
            w2 = wp.float32(1.0) - w0 - w1
            if w0 >= slack and w1 >= slack and w2 >= slack:
                z = wp.clamp(w0 * d0 + w1 * d1 + w2 * d2, wp.float32(0.0), wp.float32(1.0))
                key = (wp.int64(z * DEPTH_STEPS) << wp.int64(32)) | wp.int64(t)
                wp.atomic_min(nearest, sy * n + sx, key)
