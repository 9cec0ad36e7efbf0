/* OpenCL C twin of plate.py's Warp kernel: the core test's allowance for the grid's staircase (region.PLATE_SHELLS),
 * the same arithmetic, each sum left to right (no fused multiply-adds). Three-dimensional launch, global size
 * (nx, ny, nz): id 0 is x. */
#include "mirror.cl"

__kernel void plate(__global const float *data, __global const float *mirrored, __global const uchar *code,
                    __global const float *thick, __global const float *to_bone, __global const uchar *core,
                    const box_t box, const float level, const float shells, __global uchar *marked,
                    __global uchar *cores)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const int i = at3(z, y, x, box.ny, box.nx);
    const int c = (int)code[i];
    const int k0 = (int)core[i];
    const float t = thick[i];
    const float big = max(box.sz, max(box.sy, box.sx));
    int added = 0;
    if ((c & 4) != 0 && (c & 1) == 0 && (c & 8) != 0 && k0 == 0 && t > 0.0f && to_bone[i] > t - big) {
        float gz, gy, gx;
        gradient3(mirrored, box, z, y, x, &gz, &gy, &gx);
        const float n = sqrt(gz * gz + gy * gy + gx * gx);
        if (n > 0.0f) {
            const float nz_ = gz / n;
            const float ny_ = gy / n;
            const float nx_ = gx / n;
            const float width = min(fabs(nz_) * box.sz + fabs(ny_) * box.sy + fabs(nx_) * box.sx, big);
            if (to_bone[i] > max(t - width, 2.0f * width)) {
                added = 1;
                const float step = 0.5f * min(box.sz, min(box.sy, box.sx));
                int run[2] = {1, 1}; /* the column (this way, the other) still in the mirrored shell it starts in */
                int k = 1;
                while ((float)k * step <= shells * t + step && added == 1) {
                    for (int s = 0; s < 2; s++) {
                        const float d = (float)k * step * (1.0f - 2.0f * (float)s);
                        const float fz = (float)z + d * nz_ / box.sz;
                        const float fy = (float)y + d * ny_ / box.sy;
                        const float fx = (float)x + d * nx_ / box.sx;
                        const int scan = sample3(data, box.nz, box.ny, box.nx, fz, fy, fx, -1.0e30f) >= level;
                        const int mir = sample3(mirrored, box.nz, box.ny, box.nx, fz, fy, fx, -1.0e30f) >= level;
                        if (run[s] == 1 && !mir) run[s] = 0;
                        if (scan || (run[s] == 0 && mir)) added = 0;
                    }
                    k += 1;
                }
            }
        }
    }
    marked[i] = (uchar)(added == 1 ? 3 : k0);
    cores[i] = (uchar)((k0 == 1 || added == 1) ? 1 : 0);
}
