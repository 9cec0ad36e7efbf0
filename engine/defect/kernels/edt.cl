/* OpenCL C twins of edt.py's Warp kernels: the exact Euclidean distance transform (Felzenszwalb and Huttenlocher's
 * lower envelope of parabolas, one work-item per grid line, one pass per axis, anisotropic spacing), the same
 * arithmetic (no fused multiply-adds: bit for bit). Volumes are flat float arrays in (z, y, x) order; BIG stands for
 * "no feature on this line". One-dimensional launches: id 0 is the element (or the line). */
#pragma OPENCL FP_CONTRACT OFF

#define BIG 1.0e30f

#include "envelope.cl"

/* f = 0 at the features (mask set, or mask clear with inside), BIG elsewhere */
__kernel void features(__global const uchar *mask, const int inside, __global float *f)
{
    const int i = (int)get_global_id(0);
    int m = (int)mask[i];
    if (inside != 0) m = 1 - m;
    f[i] = m != 0 ? 0.0f : BIG;
}

/* one axis of the squared distance: g[q] = min_p (x_q - x_p)^2 + f[p] along each line (lower envelope) */
__kernel void edt_pass(__global const float *f, __global float *g, const int nz, const int ny, const int nx,
                       const int axis, const float spacing, __global int *v, __global float *zb)
{
    const int line = (int)get_global_id(0);
    int base, stride, n;
    grid_line(line, nz, ny, nx, axis, &base, &stride, &n);
    const int so = line * (n + 1);
    const int k = lower_envelope(f, base, stride, n, spacing, v, zb, so);
    if (k < 0) {
        for (int q = 0; q < n; q++) g[base + q * stride] = BIG;
    } else {
        int j = 0;
        for (int q = 0; q < n; q++) {
            const float xq = (float)q * spacing;
            while (zb[so + j + 1] < xq) j += 1;
            const int vj = v[so + j];
            const float d = xq - (float)vj * spacing;
            g[base + q * stride] = d * d + f[base + vj * stride];
        }
    }
}

/* out = sqrt(g), BIG where no feature was found */
__kernel void edt_sqrt(__global const float *g, __global float *out)
{
    const int i = (int)get_global_id(0);
    const float x = g[i];
    out[i] = x >= BIG * 0.5f ? BIG : sqrt(x);
}
