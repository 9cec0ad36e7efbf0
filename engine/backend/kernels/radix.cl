/* OpenCL C kernels of the OpenCL backend's stable sort of int64 keys with int32 values
 * (engine.backend.opencl_backend.OpenCLBackend.sort_pairs): a least-significant-digit radix sort, 4 bits a pass,
 * of the keys less their smallest (so only the bits their range spans are passed over; negative keys sort too).
 *
 * As in scan.cl, each of `chunks` work items owns the contiguous run [i * len, min((i + 1) * len, n)): it counts its
 * run's digits, the counts are scanned digit-major (every run's 0s, then every run's 1s, ...), and each work item
 * moves its run in order to its digits' places. Equal digits keep their order, so each pass, and the sort, are
 * stable. A pass reads one half of the 2 n element arrays and writes the other (`src`, `dst`: 0 or n). */

#define RADIX 16
#define DIGIT(key, base, shift) ((int)((((ulong)(key) - (ulong)(base)) >> (shift)) & (RADIX - 1)))

/* ends[i]: run i's smallest key; ends[chunks + i]: its largest (one array, read back once) */
__kernel void chunk_range(__global const long *keys, const long n, const long len, __global long *ends)
{
    const long i = get_global_id(0);
    const long a = i * len;
    const long b = min(a + len, n);
    long mn = LONG_MAX;
    long mx = LONG_MIN;
    for (long k = a; k < b; k++) {
        const long v = keys[k];
        mn = min(mn, v);
        mx = max(mx, v);
    }
    ends[i] = mn;
    ends[get_global_size(0) + i] = mx;
}

__kernel void chunk_digits(__global const long *keys, const long src, const long n, const long len, const long base,
                           const int shift, const int chunks, __global int *counts)
{
    const int i = (int)get_global_id(0);
    const long a = i * len;
    const long b = min(a + len, n);
    int c[RADIX];
    for (int d = 0; d < RADIX; d++) c[d] = 0;
    for (long k = a; k < b; k++) c[DIGIT(keys[src + k], base, shift)]++;
    for (int d = 0; d < RADIX; d++) counts[d * chunks + i] = c[d];
}

__kernel void chunk_scatter(__global long *keys, __global int *values, const long src, const long dst, const long n,
                            const long len, const long base, const int shift, const int chunks,
                            __global const int *offsets)
{
    const int i = (int)get_global_id(0);
    const long a = i * len;
    const long b = min(a + len, n);
    int at[RADIX];
    for (int d = 0; d < RADIX; d++) at[d] = offsets[d * chunks + i];
    for (long k = a; k < b; k++) {
        const long key = keys[src + k];
        const int to = at[DIGIT(key, base, shift)]++;
        keys[dst + to] = key;
        values[dst + to] = values[src + k];
    }
}
