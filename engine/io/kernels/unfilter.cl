/* OpenCL C kernel that turns PNG slices' inflated rows into samples on the device: one step of the wavefront of
 * unfilter.py's Warp kernel, the same arithmetic, layout and block sizes (see there). */

#define BLOCK 32
#define BAND 4

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
                       __global int *bad, const int height, const int width, const int bpp, const int step)
{
    const int i = (int)get_global_id(0);
    const int blocks = (width + BLOCK - 1) / BLOCK;
    const int j = i % blocks;
    const int y0 = (step - j) * BAND;
    if (y0 < 0 || y0 >= height) {
        return;
    }
    const int s = slices[i / blocks / bpp];
    const int lane = (i / blocks) % bpp;
    const long line = (long)width * bpp;
    const int x0 = j * BLOCK;
    const int x1 = min(x0 + BLOCK, width);
    for (int y = y0; y < min(y0 + BAND, height); ++y) {
        __global const uchar *src = rows + (long)s * plane + y * (1 + line);
        __global uchar *dst = out + ((long)s * height + y) * line + (bpp - 1 - lane);
        int kind = src[0];
        if (kind > 4) {
            bad[s] = 1;
            kind = 0;
        }
        src += 1 + lane;
        int a = 0;
        int c = 0;
        if (x0 > 0) {
            a = dst[(x0 - 1) * bpp];
            if (y > 0) {
                c = dst[(x0 - 1) * bpp - line];
            }
        }
        for (int x = x0; x < x1; ++x) {
            const int b = y > 0 ? dst[x * bpp - line] : 0;
            const int v = reconstruct(kind, src[x * bpp], a, b, c);
            dst[x * bpp] = (uchar)v;
            a = v;
            c = b;
        }
    }
}
