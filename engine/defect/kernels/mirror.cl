/* OpenCL C twins of mirror.py's Warp kernels: the defect's voxel rules (the mirrored scan, each voxel's class and
 * shell thickness, the cores, the grown region, the masks), the same arithmetic, each sum left to right (no fused
 * multiply-adds: bit for bit). Volumes are flat (z, y, x) arrays; three-dimensional launches have global size
 * (nx, ny, nz): id 0 is x. */
#pragma OPENCL FP_CONTRACT OFF

/* mirror.py's Mirror: q = a @ p + b on grid (x, y, z) mm, a row-major */
typedef struct {
    float a00, a01, a02, a10, a11, a12, a20, a21, a22, b0, b1, b2;
} mirror_t;

/* mirror.py's Box: a crop's shape, its first voxel in the whole grid (z, y, x), the grid's spacing (z, y, x mm) */
typedef struct {
    int nz, ny, nx, lz, ly, lx;
    float sz, sy, sx;
} box_t;

static int at3(const int z, const int y, const int x, const int ny, const int nx) { return (z * ny + y) * nx + x; }

/* trilinear sample at fractional index (z, y, x); outside beyond the array */
static float sample3(__global const float *data, const int nz, const int ny, const int nx, const float fz_,
                     const float fy_, const float fx_, const float outside)
{
    const int z0 = (int)floor(fz_);
    const int y0 = (int)floor(fy_);
    const int x0 = (int)floor(fx_);
    const float fz = fz_ - (float)z0;
    const float fy = fy_ - (float)y0;
    const float fx = fx_ - (float)x0;
    float acc = 0.0f;
    for (int c = 0; c < 8; c++) {
        const int dz = c / 4;
        const int dy = (c / 2) % 2;
        const int dx = c % 2;
        const int z = z0 + dz;
        const int y = y0 + dy;
        const int x = x0 + dx;
        const float wz = dz == 1 ? fz : 1.0f - fz;
        const float wy = dy == 1 ? fy : 1.0f - fy;
        const float wx = dx == 1 ? fx : 1.0f - fx;
        const float w = wz * wy * wx;
        float v = outside;
        if (z >= 0 && z < nz && y >= 0 && y < ny && x >= 0 && x < nx) v = data[at3(z, y, x, ny, nx)];
        acc += w * v;
    }
    return acc;
}

/* 1 when any of the 8 trilinear corners around fractional index (z, y, x) is set */
static int any_corner(__global const uchar *mask, const int nz, const int ny, const int nx, const float fz,
                      const float fy, const float fx)
{
    const int z0 = (int)floor(fz);
    const int y0 = (int)floor(fy);
    const int x0 = (int)floor(fx);
    int hit = 0;
    for (int c = 0; c < 8; c++) {
        const int z = z0 + c / 4;
        const int y = y0 + (c / 2) % 2;
        const int x = x0 + c % 2;
        if (z >= 0 && z < nz && y >= 0 && y < ny && x >= 0 && x < nx && mask[at3(z, y, x, ny, nx)] != 0) hit = 1;
    }
    return hit;
}

/* the shell's local thickness around voxel (cz, cy, cx): the diameter of the largest ball inside the shell centred
 * within reach mm of it (mirror.py's _local_thickness) */
static float local_thickness(__global const float *hdist, const int nz, const int ny, const int nx, const int cz,
                             const int cy, const int cx, const int rz, const int ry, const int rx, const float sz,
                             const float sy, const float sx, const float reach, const float slack)
{
    float best = 0.0f;
    for (int z = max(cz - rz, 0); z < min(cz + rz + 1, nz); z++) {
        const float dz = (float)(z - cz) * sz;
        for (int y = max(cy - ry, 0); y < min(cy + ry + 1, ny); y++) {
            const float dy = (float)(y - cy) * sy;
            for (int x = max(cx - rx, 0); x < min(cx + rx + 1, nx); x++) {
                const float h = hdist[at3(z, y, x, ny, nx)];
                if (2.0f * h > best) {
                    const float dx = (float)(x - cx) * sx;
                    if (sqrt(dz * dz + dy * dy + dx * dx) <= reach + slack) best = 2.0f * h;
                }
            }
        }
    }
    return best;
}

__kernel void mirror(__global const float *data, __global const uchar *skull, const box_t box,
                     __global const float *source, __global const uchar *source_skull, __global const float *hdist,
                     const box_t src, const mirror_t m, const float level, const float mid, const float outside,
                     const int rz, const int ry, const int rx, const float reach, __global float *mirrored,
                     __global uchar *code, __global float *thick)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const int i = at3(z, y, x, box.ny, box.nx);
    const float px = (float)(x + box.lx) * box.sx;
    const float py = (float)(y + box.ly) * box.sy;
    const float pz = (float)(z + box.lz) * box.sz;
    const float qx = m.a00 * px + m.a01 * py + m.a02 * pz + m.b0;
    const float qy = m.a10 * px + m.a11 * py + m.a12 * pz + m.b1;
    const float qz = m.a20 * px + m.a21 * py + m.a22 * pz + m.b2;
    const float fz = qz / box.sz - (float)src.lz;
    const float fy = qy / box.sy - (float)src.ly;
    const float fx = qx / box.sx - (float)src.lx;
    const float mv = sample3(source, src.nz, src.ny, src.nx, fz, fy, fx, outside);
    mirrored[i] = mv;
    const float v = data[i];
    int c = 0;
    if (v >= level) c |= 1;
    if (skull[i] != 0) c |= 2;
    if (mv >= level && any_corner(source_skull, src.nz, src.ny, src.nx, fz, fy, fx) != 0) c |= 4;
    if (v < mid) c |= 8;
    if (mv < mid) c |= 16;
    code[i] = (uchar)c;
    float t = 0.0f;
    const float slack = 0.5f * max(box.sz, max(box.sy, box.sx));
    if ((c & 4) != 0 && (c & 1) == 0) {
        t = local_thickness(hdist, src.nz, src.ny, src.nx, (int)round(fz), (int)round(fy), (int)round(fx), rz, ry, rx,
                            box.sz, box.sy, box.sx, reach, slack);
    } else if ((c & 2) != 0 && (c & 4) == 0) {
        t = local_thickness(hdist, src.nz, src.ny, src.nx, z + box.lz - src.lz, y + box.ly - src.ly,
                            x + box.lx - src.lx, rz, ry, rx, box.sz, box.sy, box.sx, reach, slack);
    }
    thick[i] = t;
}

/* the cores: 1 missing bone, 2 bone on this side only (mirror.py's core_kernel); one-dimensional */
__kernel void core(__global const uchar *code, __global const float *thick, __global const float *to_bone,
                   __global const float *to_mirror, __global uchar *out)
{
    const int i = (int)get_global_id(0);
    const int c = (int)code[i];
    const float t = thick[i];
    int k = 0;
    if ((c & 4) != 0 && (c & 1) == 0 && (c & 8) != 0 && to_bone[i] > t) k = 1;
    else if ((c & 2) != 0 && (c & 4) == 0 && (c & 16) != 0 && to_mirror[i] > t) k = 2;
    out[i] = (uchar)k;
}

static float value3(__global const float *a, const int nz, const int ny, const int nx, const int z, const int y,
                    const int x)
{
    return a[at3(clamp(z, 0, nz - 1), clamp(y, 0, ny - 1), clamp(x, 0, nx - 1), ny, nx)];
}

/* the mirrored field's gradient at voxel (z, y, x) of the box, Sobel 3x3x3 in mm: (z, y, x) components */
static void gradient3(__global const float *mirrored, const box_t box, const int z, const int y, const int x,
                      float *gz_, float *gy_, float *gx_)
{
    float gz = 0.0f, gy = 0.0f, gx = 0.0f;
    for (int k = 0; k < 27; k++) {
        const int dz = k / 9 - 1;
        const int dy = (k / 3) % 3 - 1;
        const int dx = k % 3 - 1;
        const float v = value3(mirrored, box.nz, box.ny, box.nx, z + dz, y + dy, x + dx);
        const float wz = (float)(2 - dy * dy) * (float)(2 - dx * dx);
        const float wy = (float)(2 - dz * dz) * (float)(2 - dx * dx);
        const float wx = (float)(2 - dz * dz) * (float)(2 - dy * dy);
        gz = gz + (float)dz * wz * v / box.sz;
        gy = gy + (float)dy * wy * v / box.sy;
        gx = gx + (float)dx * wx * v / box.sx;
    }
    *gz_ = gz;
    *gy_ = gy;
    *gx_ = gx;
}

/* the candidate region (mirror.py's grow_kernel) */
__kernel void grow(__global const float *data, __global const float *mirrored, __global const uchar *code,
                   __global const float *thick, __global const float *to_core, const box_t box, const float level,
                   const float reach, __global uchar *grown)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const int i = at3(z, y, x, box.ny, box.nx);
    const int c = (int)code[i];
    int g = 0;
    const float t = thick[i];
    if ((c & 4) != 0 && (c & 1) == 0 && to_core[i] <= t + reach) {
        g = 1;
        float gz, gy, gx;
        gradient3(mirrored, box, z, y, x, &gz, &gy, &gx);
        const float n = sqrt(gz * gz + gy * gy + gx * gx);
        if (n > 0.0f) {
            const float nz_ = gz / n;
            const float ny_ = gy / n;
            const float nx_ = gx / n;
            const float step = 0.5f * min(box.sz, min(box.sy, box.sx));
            int k = 1;
            while ((float)k * step <= 0.5f * t + step && g == 1) {
                for (int s = 0; s < 2; s++) {
                    const float d = (float)k * step * (1.0f - 2.0f * (float)s);
                    const float fz = (float)z + d * nz_ / box.sz;
                    const float fy = (float)y + d * ny_ / box.sy;
                    const float fx = (float)x + d * nx_ / box.sx;
                    if (sample3(data, box.nz, box.ny, box.nx, fz, fy, fx, -1.0e30f) >= level) g = 0;
                }
                k += 1;
            }
        }
    }
    grown[i] = (uchar)g;
}

/* out = 1 where src == value; one-dimensional */
__kernel void select_value(__global const uchar *src, const int value, __global uchar *out)
{
    const int i = (int)get_global_id(0);
    out[i] = (int)src[i] == value ? 1 : 0;
}

/* out = 1 where any of bits is set in src; one-dimensional */
__kernel void any_bits(__global const uchar *src, const int bits, __global uchar *out)
{
    const int i = (int)get_global_id(0);
    out[i] = ((int)src[i] & bits) != 0 ? 1 : 0;
}

/* 1 at the shell's middle: inside voxels whose inner distance is at least each of their 26 neighbours' */
__kernel void ridge(__global const float *hdist, const int nz, const int ny, const int nx, __global uchar *out)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const float h = hdist[at3(z, y, x, ny, nx)];
    int r = 0;
    if (h > 0.0f) {
        r = 1;
        for (int c = 0; c < 27; c++) {
            const int zz = z + c / 9 - 1;
            const int yy = y + (c / 3) % 3 - 1;
            const int xx = x + c % 3 - 1;
            if (zz >= 0 && zz < nz && yy >= 0 && yy < ny && xx >= 0 && xx < nx && hdist[at3(zz, yy, xx, ny, nx)] > h)
                r = 0;
        }
    }
    out[at3(z, y, x, ny, nx)] = (uchar)r;
}
