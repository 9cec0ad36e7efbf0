/* OpenCL C kernels that turn PNG slices' inflated rows into samples on the device: the same arithmetic as
 * unfilter.py's Warp kernels (see there for the layout). rows: slice s's plane at s * plane bytes. */

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

__kernel void unfilter(__global uchar *rows, const int plane, __global const int *slices, __global int *bad,
                       const int height, const int width, const int bpp)
{
    const int i = (int)get_global_id(0);
    const int s = slices[i / bpp];
    const int lane = i % bpp;
    const long stride = 1 + (long)width * bpp;
    __global uchar *base = rows + (long)s * plane;
    for (int y = 0; y < height; ++y) {
        __global uchar *row = base + y * stride;
        const int kind = row[0];
        if (kind > 4) {
            bad[s] = 1;
            return;
        }
        int a = 0;
        int c = 0;
        for (int x = 0; x < width; ++x) {
            const long p = 1 + (long)x * bpp + lane;
            const int b = y > 0 ? row[p - stride] : 0;
            const int v = reconstruct(kind, row[p], a, b, c);
            row[p] = (uchar)v;
            a = v;
            c = b;
        }
    }
}

/* Global size (line bytes, height, slices): byte x of line y of slice slices[j], native (little-endian) order. */
__kernel void pack(__global const uchar *rows, const int plane, __global const int *slices, __global uchar *out,
                   const int height, const int width, const int bpp)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int s = slices[get_global_id(2)];
    const long line = (long)width * bpp;
    const int lane = bpp - 1 - x % bpp;
    out[((long)s * height + y) * line + x] = rows[(long)s * plane + y * (1 + line) + 1 + (x / bpp) * bpp + lane];
}
