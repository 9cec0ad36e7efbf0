/* The lower envelope of the parabolas of one grid line, shared by edt.cl and plane.cl (edt.py's lower_envelope and
 * _line, the same arithmetic). The including file defines BIG ("no feature") and turns FP_CONTRACT off. */

/* (first flat index, stride, length) of grid line `line` along `axis` of a (nz, ny, nx) volume */
static void grid_line(const int line, const int nz, const int ny, const int nx, const int axis, int *base,
                      int *stride, int *n)
{
    if (axis == 2) {
        *base = line * nx; *stride = 1; *n = nx;
    } else if (axis == 1) {
        const int z = line / nx;
        const int x = line - z * nx;
        *base = z * ny * nx + x; *stride = nx; *n = ny;
    } else {
        *base = line; *stride = ny * nx; *n = nz;
    }
}

/* the lower envelope of the line's parabolas (x - x_p)^2 + f[p]: their positions in v and breakpoints in zb, from
 * so; the index of the last parabola, -1 where the line has no feature */
static int lower_envelope(__global const float *f, const int base, const int stride, const int n,
                          const float spacing, __global int *v, __global float *zb, const int so)
{
    int k = -1;
    for (int q = 0; q < n; q++) {
        const float fq = f[base + q * stride];
        if (fq < BIG * 0.5f) {
            const float xq = (float)q * spacing;
            if (k < 0) {
                k = 0;
                v[so] = q;
                zb[so] = -BIG;
                zb[so + 1] = BIG;
            } else {
                int vk = v[so + k];
                float xv = (float)vk * spacing;
                float s = ((fq + xq * xq) - (f[base + vk * stride] + xv * xv)) / (2.0f * (xq - xv));
                while (s <= zb[so + k]) {
                    k -= 1;
                    vk = v[so + k];
                    xv = (float)vk * spacing;
                    s = ((fq + xq * xq) - (f[base + vk * stride] + xv * xv)) / (2.0f * (xq - xv));
                }
                k += 1;
                v[so + k] = q;
                zb[so + k] = s;
                zb[so + k + 1] = BIG;
            }
        }
    }
    return k;
}
