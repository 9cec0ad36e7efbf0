/* OpenCL C twins of the decimation's own device-mesh kernels: quadrics.py's scatter_kept and collapse.py's
 * lock_vertices. The stars, vertex classes, compaction and bounds are the surface package's kernels
 * (engine/surface/kernels/topology.cl and compaction.cl, named in engine.decimation.kernel_specs).
 * Host side: engine.decimation.meshops. Quadrics are 10 doubles per vertex. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#include "common.cl" /* LOCKED, DEAD (engine/backend/kernels) */

/* For a compaction that carries the quadrics: each kept vertex's old index and its quadric. */
__kernel void scatter_kept(__global const int *count, __global const int *slot, __global const double *quad,
                           __global int *kept, __global double *out_quad)
{
    const int v = get_global_id(0);
    if (count[v] > 0) {
        const int s = slot[v];
        kept[s] = v;
        for (int k = 0; k < 10; k++) out_quad[10 * s + k] = quad[10 * v + k];
    }
}

/* Vertices the caller pins (a tile's border): LOCKED, so no collapse moves, removes or extends them. */
__kernel void lock_vertices(__global const int *lock, __global int *state)
{
    const int v = get_global_id(0);
    if (lock[v] != 0 && state[v] != DEAD) state[v] = LOCKED;
}
