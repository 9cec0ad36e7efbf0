/* OpenCL C twins of layout.py's rasterize_nearest (the preview's z-buffer), the same arithmetic (no fused
 * multiply-adds: bit for bit). Each work-item scan-converts one front-facing triangle (image coordinates, y
 * downward; depth in [0, 1], smaller is nearer) into an n x n z-buffer; a pixel keeps the nearest triangle, ties to
 * the lower index, whatever the launch order:
 *   rasterize_nearest: the atomic min of (depth code << 32) | triangle (64-bit atomics: where the device has
 *     cl_khr_int64_extended_atomics), as the Warp kernel;
 *   raster_depth, then raster_triangle: without 64-bit atomics, the atomic min of the depth code (int), then of the
 *     triangle among those whose code is that minimum (the same pixel, the same winner).
 * One-dimensional launches: id 0 is the triangle. */
#pragma OPENCL FP_CONTRACT OFF

#define DEPTH_STEPS 1073741823.0f /* depth in [0, 1] quantised to 30 bits */
#define SLACK (-1.0e-6f)          /* a sample on a shared edge belongs to both triangles: no pinholes */

/* the triangle's corners, its doubled signed area (negative: front-facing) and its pixel box; 0 when back-facing */
static int setup(__global const float *px, __global const float *py, __global const int *tris, const int t,
                 const int n, float *x, float *y, int3 *f, float *area, int4 *bb)
{
    *f = vload3(t, tris);
    x[0] = px[f->x]; x[1] = px[f->y]; x[2] = px[f->z];
    y[0] = py[f->x]; y[1] = py[f->y]; y[2] = py[f->z];
    *area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]);
    if (!(*area < 0.0f)) return 0; /* counter-clockwise in y-up is clockwise in the y-down image: front faces */
    bb->x = max((int)ceil(fmin(x[0], fmin(x[1], x[2])) - 0.5f), 0);
    bb->y = min((int)floor(fmax(x[0], fmax(x[1], x[2])) - 0.5f), n - 1);
    bb->z = max((int)ceil(fmin(y[0], fmin(y[1], y[2])) - 0.5f), 0);
    bb->w = min((int)floor(fmax(y[0], fmax(y[1], y[2])) - 0.5f), n - 1);
    return 1;
}

/* the depth code of pixel (sx, sy), or -1 where its centre is outside the triangle */
static int code_at(const float *x, const float *y, const float *d, const float area, const int sx, const int sy)
{
    const float cy = (float)sy + 0.5f;
    const float cx = (float)sx + 0.5f;
    const float w0 = ((x[1] - cx) * (y[2] - cy) - (x[2] - cx) * (y[1] - cy)) / area;
    const float w1 = ((x[2] - cx) * (y[0] - cy) - (x[0] - cx) * (y[2] - cy)) / area;
    const float w2 = 1.0f - w0 - w1;
    if (!(w0 >= SLACK && w1 >= SLACK && w2 >= SLACK)) return -1;
    const float z = clamp(w0 * d[0] + w1 * d[1] + w2 * d[2], 0.0f, 1.0f);
    return (int)(long)(z * DEPTH_STEPS);
}

#define RASTER_LOOP(BODY)                                                                                       \
    float x[3], y[3], d[3], area;                                                                               \
    int3 f;                                                                                                     \
    int4 bb;                                                                                                    \
    if (!setup(px, py, tris, t, n, x, y, &f, &area, &bb)) return;                                               \
    d[0] = depth[f.x]; d[1] = depth[f.y]; d[2] = depth[f.z];                                                    \
    for (int sy = bb.z; sy <= bb.w; sy++)                                                                       \
        for (int sx = bb.x; sx <= bb.y; sx++) {                                                                 \
            const int code = code_at(x, y, d, area, sx, sy);                                                    \
            if (code >= 0) { BODY }                                                                             \
        }

#ifdef cl_khr_int64_extended_atomics
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable
__kernel void rasterize_nearest(__global const float *px, __global const float *py, __global const float *depth,
                                __global const int *tris, const int n, __global long *nearest)
{
    const int t = (int)get_global_id(0);
    RASTER_LOOP(atom_min(&nearest[sy * n + sx], ((long)code << 32) | (long)t);)
}
#endif

__kernel void raster_depth(__global const float *px, __global const float *py, __global const float *depth,
                           __global const int *tris, const int n, __global int *zbuf)
{
    const int t = (int)get_global_id(0);
    RASTER_LOOP(atomic_min(&zbuf[sy * n + sx], code);)
}

__kernel void raster_triangle(__global const float *px, __global const float *py, __global const float *depth,
                              __global const int *tris, const int n, __global const int *zbuf, __global int *winner)
{
    const int t = (int)get_global_id(0);
    RASTER_LOOP(if (zbuf[sy * n + sx] == code) atomic_min(&winner[sy * n + sx], t);)
}
