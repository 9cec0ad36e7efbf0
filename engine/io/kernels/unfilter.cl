/* OpenCL C kernel that turns PNG slices' inflated rows into samples on the device: the same arithmetic and layout
 * as unfilter.py's Warp kernel (see there). */

#define CHUNK 32

static int reconstruct(const int kind, const int raw, const int a, const int b, const int c)
{
    int pred = 0;
    if (kind == 1) {
        pred = a;
    } else if (kind == 2) {
        pred = b;
    } else if (kind == 3) {
        pred = (a + b) >> 1;
    } else if (kind == 4) {
        const int p = a + b - c;
        const int pa = abs(p - a);
        const int pb = abs(p - b);
        const int pc = abs(p - c);
        pred = (pa <= pb && pa <= pc) ? a : (pb <= pc ? b : c);
    }
    return (raw + pred) & 255;
}

__kernel void unfilter(__global const uchar *rows, const int plane, __global const int *slices, __global uchar *out,
                       __global int *bad, const int height, const int width, const int bpp)
{
    const int i = (int)get_global_id(0);
    const int s = slices[i / bpp];
    const int lane = i % bpp;
    const long line = (long)width * bpp;
    for (int y = 0; y < height; ++y) {
        __global const uchar *src = rows + (long)s * plane + y * (1 + line);
        __global uchar *dst = out + ((long)s * height + y) * line + (bpp - 1 - lane);
        const int kind = src[0];
        if (kind > 4) {
            bad[s] = 1;
            return;
        }
        src += 1 + lane;
        int a = 0;
        int c = 0;
        for (int x0 = 0; x0 < width; x0 += CHUNK) {
            int raw[CHUNK];
            int up[CHUNK];
#pragma unroll
            for (int j = 0; j < CHUNK; ++j) {
                const int x = x0 + j;
                raw[j] = x < width ? src[x * bpp] : 0;
                up[j] = (x < width && y > 0) ? dst[x * bpp - line] : 0;
            }
#pragma unroll
            for (int j = 0; j < CHUNK; ++j) {
                const int x = x0 + j;
                if (x < width) {
                    const int v = reconstruct(kind, raw[j], a, up[j], c);
                    dst[x * bpp] = (uchar)v;
                    a = v;
                    c = up[j];
                }
            }
        }
    }
}
