/* OpenCL C twins of compaction.py's Warp kernels: drop removed faces and unused vertices, keeping the order of the
 * rest, and the bounding box. Arrays of vec3 / vec3i are packed float / int triples. */
#pragma OPENCL FP_CONTRACT OFF

__kernel void alive_flags(__global const int *faces, __global int *flag)
{
    const int f = get_global_id(0);
    flag[f] = faces[3 * (long)f] >= 0 ? 1 : 0;
}

__kernel void scatter_faces(__global const int *faces, __global const int *slot, __global int *out)
{
    const int f = get_global_id(0);
    if (faces[3 * (long)f] >= 0) {
        const long s = 3 * (long)slot[f];
        for (int k = 0; k < 3; k++) out[s + k] = faces[3 * (long)f + k];
    }
}

__kernel void used_flags(__global const int *count, __global int *flag)
{
    const int v = get_global_id(0);
    flag[v] = count[v] > 0 ? 1 : 0;
}

__kernel void scatter_vertices(__global const float *pos, __global const int *count, __global const int *slot,
                               __global float *out)
{
    const int v = get_global_id(0);
    if (count[v] > 0) {
        const long s = 3 * (long)slot[v];
        for (int k = 0; k < 3; k++) out[s + k] = pos[3 * (long)v + k];
    }
}

__kernel void remap_faces(__global int *faces, __global const int *slot)
{
    const int f = get_global_id(0);
    for (int k = 0; k < 3; k++) faces[3 * (long)f + k] = slot[faces[3 * (long)f + k]];
}

/* float minimum / maximum through compare-and-swap of the bits (order-independent results) */
static void atomic_min_float(volatile __global float *p, float v)
{
    union { float f; int i; } old, val;
    val.f = v;
    old.f = *p;
    while (v < old.f) {
        const int seen = atomic_cmpxchg((volatile __global int *)p, old.i, val.i);
        if (seen == old.i) break;
        old.i = seen;
    }
}

static void atomic_max_float(volatile __global float *p, float v)
{
    union { float f; int i; } old, val;
    val.f = v;
    old.f = *p;
    while (v > old.f) {
        const int seen = atomic_cmpxchg((volatile __global int *)p, old.i, val.i);
        if (seen == old.i) break;
        old.i = seen;
    }
}

/* box[0] = component-wise minimum, box[1] = maximum */
__kernel void bounds_kernel(__global const float *pos, __global float *box)
{
    const int v = get_global_id(0);
    for (int k = 0; k < 3; k++) {
        atomic_min_float(&box[k], pos[3 * (long)v + k]);
        atomic_max_float(&box[3 + k], pos[3 * (long)v + k]);
    }
}
