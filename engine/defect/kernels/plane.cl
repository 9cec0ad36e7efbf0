/* OpenCL C twins of plane.py's Warp kernels: the symmetry plane's closest-feature transform (edt.cl's lower
 * envelope carrying each voxel's feature rank) and its nearest-surface query, the same arithmetic (no fused
 * multiply-adds: bit for bit). Volumes are flat (z, y, x) arrays; points are grid (x, y, z) mm, three floats each.
 * One-dimensional launches: id 0 is the feature, the line or the point. */
#pragma OPENCL FP_CONTRACT OFF

#define BIG 1.0e30f

#include "envelope.cl"

/* mirror.py's Box: a grid's shape, its first voxel (z, y, x; 0 here), the spacing (z, y, x mm) */
typedef struct {
    int nz, ny, nx, lz, ly, lx;
    float sz, sy, sx;
} box_t;

/* f = 0 and rank = the feature's rank at each feature voxel (f = BIG and rank = -1 elsewhere, set before) */
__kernel void seed(__global const int *features, __global float *f, __global int *rank)
{
    const int i = (int)get_global_id(0);
    const int at = features[i];
    f[at] = 0.0f;
    rank[at] = i;
}

/* one axis of the closest-feature transform: edt_pass's lower envelope, each voxel taking the rank fr of the voxel
 * whose parabola it lies under into gr */
__kernel void cft_pass(__global const float *f, __global float *g, __global const int *fr, __global int *gr,
                       const int nz, const int ny, const int nx, const int axis, const float spacing,
                       __global int *v, __global float *zb)
{
    const int line = (int)get_global_id(0);
    int base, stride, n;
    grid_line(line, nz, ny, nx, axis, &base, &stride, &n);
    const int so = line * (n + 1);
    const int k = lower_envelope(f, base, stride, n, spacing, v, zb, so);
    if (k < 0) {
        for (int q = 0; q < n; q++) {
            g[base + q * stride] = BIG;
            gr[base + q * stride] = -1;
        }
    } else {
        int j = 0;
        for (int q = 0; q < n; q++) {
            const float xq = (float)q * spacing;
            while (zb[so + j + 1] < xq) j += 1;
            const int vj = v[so + j];
            const float d = xq - (float)vj * spacing;
            g[base + q * stride] = d * d + f[base + vj * stride];
            gr[base + q * stride] = fr[base + vj * stride];
        }
    }
}

/* squared distance (mm^2) from the point (x, y, z mm) to the centre of the voxel at flat index at */
static float dist2(const int at, const box_t box, const float px, const float py, const float pz)
{
    const int fz = at / (box.ny * box.nx);
    const int rest = at - fz * (box.ny * box.nx);
    const int fy = rest / box.nx;
    const int fx = rest - fy * box.nx;
    const float dx = px - (float)fx * box.sx;
    const float dy = py - (float)fy * box.sy;
    const float dz = pz - (float)fz * box.sz;
    return dx * dx + dy * dy + dz * dz;
}

/* the voxels (first, last along one axis, clamped into the grid) whose centres may lie within reach mm of p */
static int2 span(const float p, const float reach, const float s, const int n)
{
    const int lo = clamp((int)floor((p - reach) / s), 0, n - 1);
    const int hi = clamp((int)floor((p + reach) / s) + 1, 0, n - 1);
    return (int2)(lo, hi);
}

/* the nearest of the closest features of the 8 voxels around the point (x, y, z mm; clamped into the grid), ties
 * to the lower rank: its rank (-1 where there are none), its squared distance in *best */
static int bound(const float px, const float py, const float pz, __global const int *rank,
                 __global const int *features, const box_t box, float *best)
{
    const int z0 = (int)floor(pz / box.sz);
    const int y0 = (int)floor(py / box.sy);
    const int x0 = (int)floor(px / box.sx);
    float b = BIG;
    int pick = -1;
    for (int c = 0; c < 8; c++) {
        const int z = clamp(z0 + c / 4, 0, box.nz - 1);
        const int y = clamp(y0 + (c / 2) % 2, 0, box.ny - 1);
        const int x = clamp(x0 + c % 2, 0, box.nx - 1);
        const int r = rank[(z * box.ny + y) * box.nx + x];
        if (r >= 0) {
            const float d2 = dist2(features[r], box, px, py, pz);
            if (d2 < b || (d2 == b && r < pick)) {
                b = d2;
                pick = r;
            }
        }
    }
    *best = b;
    return pick;
}

/* one of parts work-items of point id / parts: the nearest feature (ties to the lower rank) among the closest
 * features of the 8 voxels around the point (bound) and the voxels of every parts-th row (z, y) of the box whose
 * centres may lie within that bound (a feature is its own closest feature, so the nearest is among them all), where
 * the box holds at most max_scan voxels; else the bound's feature. nearest_join takes the point's nearest over its
 * parts: the order of the looks does not change the answer. */
__kernel void nearest_part(__global const float *points, __global const int *rank, __global const int *features,
                           const box_t box, const int max_scan, const int parts, __global float *part_d2,
                           __global int *part_rank)
{
    const int tid = (int)get_global_id(0);
    const int i = tid / parts;
    const int k = tid - i * parts;
    const float px = points[3 * i];
    const float py = points[3 * i + 1];
    const float pz = points[3 * i + 2];
    float best;
    int pick = bound(px, py, pz, rank, features, box, &best);
    if (pick >= 0) {
        const float reach = sqrt(best);
        const int2 sz = span(pz, reach, box.sz, box.nz);
        const int2 sy = span(py, reach, box.sy, box.ny);
        const int2 sx = span(px, reach, box.sx, box.nx);
        const int ny = sy.y - sy.x + 1;
        const int rows = (sz.y - sz.x + 1) * ny;
        if (rows * (sx.y - sx.x + 1) <= max_scan) {
            for (int row = k; row < rows; row += parts) {
                const int vz = sz.x + row / ny;
                const int vy = sy.x + row - (row / ny) * ny;
                for (int vx = sx.x; vx <= sx.y; vx++) {
                    const int r = rank[(vz * box.ny + vy) * box.nx + vx];
                    if (r >= 0 && r != pick) {
                        const float d2 = dist2(features[r], box, px, py, pz);
                        if (d2 < best || (d2 == best && r < pick)) {
                            best = d2;
                            pick = r;
                        }
                    }
                }
            }
        }
    }
    part_d2[tid] = best;
    part_rank[tid] = pick;
}

/* out[i]: the nearest of point i's parts' features (ties to the lower rank), -1 where there are none */
__kernel void nearest_join(__global const float *part_d2, __global const int *part_rank, const int parts,
                           __global int *out)
{
    const int i = (int)get_global_id(0);
    float best = BIG;
    int pick = -1;
    for (int k = 0; k < parts; k++) {
        const int r = part_rank[i * parts + k];
        const float d2 = part_d2[i * parts + k];
        if (r >= 0 && (pick < 0 || d2 < best || (d2 == best && r < pick))) {
            best = d2;
            pick = r;
        }
    }
    out[i] = pick;
}

/* 1 where voxel (z, y, x) is in the grid and set, else 0 */
static int is_set(__global const uchar *mask, const int nz, const int ny, const int nx, const int z, const int y,
                  const int x)
{
    if (z < 0 || z >= nz || y < 0 || y >= ny || x < 0 || x >= nx) return 0;
    return mask[(z * ny + y) * nx + x] != 0 ? 1 : 0;
}

/* flags = 1 at the set voxels (with surface: only those with a face neighbour clear or outside the grid), else 0 */
__kernel void flags(__global const uchar *mask, const int nz, const int ny, const int nx, const int surface,
                    __global int *out)
{
    const int i = (int)get_global_id(0);
    const int z = i / (ny * nx);
    const int rest = i - z * (ny * nx);
    const int y = rest / nx;
    const int x = rest - y * nx;
    int f = is_set(mask, nz, ny, nx, z, y, x);
    if (f != 0 && surface != 0) {
        const int inner = is_set(mask, nz, ny, nx, z - 1, y, x) * is_set(mask, nz, ny, nx, z + 1, y, x)
                          * is_set(mask, nz, ny, nx, z, y - 1, x) * is_set(mask, nz, ny, nx, z, y + 1, x)
                          * is_set(mask, nz, ny, nx, z, y, x - 1) * is_set(mask, nz, ny, nx, z, y, x + 1);
        f = 1 - inner;
    }
    out[i] = f;
}

/* the Sobel smoothing weight of an offset across the derivative's axis: 1, 2, 1 */
static int weight(const int o) { return o == 0 ? 2 : 1; }

/* the mask's 3x3x3 Sobel gradient (x, y, z; integer, the grid outside clear) at flat voxel at[i] */
__kernel void sobel(__global const uchar *mask, const int nz, const int ny, const int nx, __global const int *at,
                    __global int *out)
{
    const int i = (int)get_global_id(0);
    const int a = at[i];
    const int z = a / (ny * nx);
    const int rest = a - z * (ny * nx);
    const int y = rest / nx;
    const int x = rest - y * nx;
    int gx = 0, gy = 0, gz = 0;
    for (int c = 0; c < 27; c++) {
        const int dz = c / 9 - 1;
        const int dy = (c / 3) % 3 - 1;
        const int dx = c % 3 - 1;
        if (is_set(mask, nz, ny, nx, z + dz, y + dy, x + dx) != 0) {
            gx += weight(dy) * weight(dz) * dx;
            gy += weight(dx) * weight(dz) * dy;
            gz += weight(dx) * weight(dy) * dz;
        }
    }
    out[3 * i] = gx;
    out[3 * i + 1] = gy;
    out[3 * i + 2] = gz;
}
