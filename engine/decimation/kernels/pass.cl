/* What price.cl and claims.cl (a decimation pass) both use (`#include "pass.cl"`, inlined once by
 * engine.backend.opencl_backend): the vertex classes and face helpers of engine/backend/kernels/common.cl, a
 * half-edge's ends, the cost histogram's bin shift, the tie-breaking hash and the candidate listing. */

#include "common.cl"

#define HIST_SHIFT 15

/* a well-mixed 32-bit hash of x (the tie-break between equal costs) */
static long mix32(const int x)
{
    uint h = (uint)x;
    h = h ^ (h >> 16);
    h = h * 0x7FEB352Du;
    h = h ^ (h >> 15);
    h = h * 0x846CA68Bu;
    h = h ^ (h >> 16);
    return (long)h;
}

/* the half-edge listed at i if it is still a candidate of the wanted kind, else -1 */
static int listed(__global const int *listing, __global const int *n_listed, __global const int *cand, const int want,
                  const int i)
{
    int h = -1;
    if (i < n_listed[0] && cand[listing[i]] == want) h = listing[i];
    return h;
}

/* half-edge h = 3 f + k runs from corner k of face f to the next corner */
static int2 edge_ends(__global const int *faces, const int h)
{
    const int f = h / 3;
    const int k = h - 3 * f;
    return (int2)(faces[3 * f + k], faces[3 * f + (k + 1) % 3]);
}
