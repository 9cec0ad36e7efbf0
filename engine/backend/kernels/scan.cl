/* OpenCL C kernels of the OpenCL backend's exclusive scan and stream compaction
 * (engine.backend.opencl_backend.OpenCLBackend.exclusive_scan / compact).
 *
 * The scan runs in three launches over `chunks` work items, each owning the contiguous run
 * [i * len, min((i + 1) * len, n)): its sum, then one work item scans the sums (a few thousand) and writes the total
 * after them, then each work item writes its run's exclusive prefix. Integer sums: the result does not depend on
 * the chunking. */

__kernel void chunk_sums(__global const int *src, const long n, const long len, __global int *sums)
{
    const long i = get_global_id(0);
    const long lo = i * len;
    const long hi = min(lo + len, n);
    int s = 0;
    for (long k = lo; k < hi; k++) s += src[k];
    sums[i] = s;
}

__kernel void scan_sums(__global int *sums, const int chunks)
{
    int run = 0;
    for (int i = 0; i < chunks; i++) {
        const int s = sums[i];
        sums[i] = run;
        run += s;
    }
    sums[chunks] = run; /* the total */
}

__kernel void chunk_scan(__global const int *src, const long n, const long len, __global const int *sums,
                         __global int *dst)
{
    const long i = get_global_id(0);
    const long lo = i * len;
    const long hi = min(lo + len, n);
    int run = sums[i];
    for (long k = lo; k < hi; k++) {
        const int s = src[k];
        dst[k] = run;
        run += s;
    }
}

__kernel void compact(__global const int *flags, __global const int *pos, __global int *indices,
                      __global int *ranks)
{
    const int i = (int)get_global_id(0);
    if (flags[i] != 0) {
        indices[pos[i]] = i;
        ranks[i] = pos[i];
    } else {
        ranks[i] = -1;
    }
}
