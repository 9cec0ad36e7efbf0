/* OpenCL C twins of cluster.py's Warp kernels (quadric vertex clustering and the piece census; read that file's
 * docstrings). Host side: engine.decimation.cluster. The same arithmetic in the same order as the Warp kernels on
 * the CPU (no fused multiply-adds; the determinant and inverse of linalg.cl, as Warp's native code computes them).
 * Layouts: vec3 arrays are packed float triples, vec3i packed int triples, a quadric 10 doubles; `lo` a struct of
 * 3 floats, the origin a struct of 3 doubles. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define CELL_MAX 2097151
#define DROPPED 0x7FFFFFFFFFFFFFFFL

typedef struct {
    float x, y, z;
} lo_t;

#include "linalg.cl" /* origin_t, d3, dot3, cross3, dmin, dmax, det3, solve3 */

static int imin(const int a, const int b) { return a < b ? a : b; }
static int imax(const int a, const int b) { return a > b ? a : b; }

static double q_eval(const double *q, const double3 p)
{
    const double x = p.x, y = p.y, z = p.z, two = 2.0;
    return q[0] * x * x + two * q[1] * x * y + two * q[2] * x * z + two * q[3] * x + q[4] * y * y +
           two * q[5] * y * z + two * q[6] * y + q[7] * z * z + two * q[8] * z + q[9];
}

static int cell(const float p) { return imin(imax((int)floor(p), 0), CELL_MAX); }

__kernel void cell_keys(__global const float *pos, const lo_t lo, const float inv_h, __global long *keys,
                        __global int *values)
{
    const int v = get_global_id(0);
    const float pz = (pos[3 * v] - lo.x) * inv_h;
    const float py = (pos[3 * v + 1] - lo.y) * inv_h;
    const float px = (pos[3 * v + 2] - lo.z) * inv_h;
    keys[v] = (long)cell(px) | ((long)cell(py) << 21) | ((long)cell(pz) << 42);
    values[v] = v;
}

__kernel void assign_cells(__global const int *flag, __global const int *scan, __global const int *order,
                           __global int *cell_of, __global int *start)
{
    const int i = get_global_id(0);
    const int c = scan[i] + flag[i] - 1;
    cell_of[order[i]] = c;
    if (flag[i] == 1) start[c] = i;
}

__kernel void face_cells(__global const int *faces, __global const int *cell_of, __global int *out,
                         __global long *keys, __global int *values)
{
    const int f = get_global_id(0);
    const int a = cell_of[faces[3 * f]], b = cell_of[faces[3 * f + 1]], c = cell_of[faces[3 * f + 2]];
    vstore3((int3)(a, b, c), f, out);
    values[f] = f;
    const int lo = imin(imin(a, b), c);
    const int hi = imax(imax(a, b), c);
    const int mid = a + b + c - lo - hi;
    keys[f] = DROPPED;
    if (a != b && b != c && a != c) keys[f] = (long)lo | ((long)mid << 21) | ((long)hi << 42);
}

__kernel void run_starts(__global const long *keys, __global int *flag)
{
    const int i = get_global_id(0);
    flag[i] = 0;
    if (keys[i] != DROPPED && (i == 0 || keys[i] != keys[i - 1])) flag[i] = 1;
}

__kernel void gather_faces(__global const int *flag, __global const int *scan, __global const int *order,
                           __global const int *cells, __global int *out)
{
    const int i = get_global_id(0);
    if (flag[i] == 1) vstore3(vload3(order[i], cells), scan[i], out);
}

__kernel void cell_positions(__global const float *pos, __global const double *quad, __global const int *order,
                             __global const int *start, const int n_sorted, const int n_cells, const origin_t origin,
                             __global float *out)
{
    const int c = get_global_id(0);
    const int lo = start[c];
    const int hi = c + 1 < n_cells ? start[c + 1] : n_sorted;
    double q[10] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
    double3 mean = d3(0.0, 0.0, 0.0);
    double3 bmin = d3(1.0e30, 1.0e30, 1.0e30), bmax = d3(-1.0e30, -1.0e30, -1.0e30);
    for (int i = lo; i < hi; i++) {
        const int v = order[i];
        for (int k = 0; k < 10; k++) q[k] = q[k] + quad[10 * v + k];
        const double3 pd = d3((double)pos[3 * v] - origin.x, (double)pos[3 * v + 1] - origin.y,
                              (double)pos[3 * v + 2] - origin.z);
        mean = mean + pd;
        bmin = d3(dmin(bmin.x, pd.x), dmin(bmin.y, pd.y), dmin(bmin.z, pd.z));
        bmax = d3(dmax(bmax.x, pd.x), dmax(bmax.y, pd.y), dmax(bmax.z, pd.z));
    }
    const double n = (double)(hi - lo);
    mean = d3(mean.x / n, mean.y / n, mean.z / n);
    double3 best = mean;
    const double m[9] = {q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7]};
    const double scale = (q[0] + q[4] + q[7]) / 3.0;
    const double det = det3(m);
    if (scale > 0.0 && fabs(det) > 1.0e-6 * scale * scale * scale) {
        double3 x = solve3(m, det, d3(q[3], q[6], q[8]));
        x = d3(dmin(dmax(x.x, bmin.x), bmax.x), dmin(dmax(x.y, bmin.y), bmax.y), dmin(dmax(x.z, bmin.z), bmax.z));
        if (q_eval(q, x) <= q_eval(q, mean)) best = x;
    }
    vstore3((float3)((float)(best.x + origin.x), (float)(best.y + origin.y), (float)(best.z + origin.z)), c, out);
}

/* The used vertices of every piece (`used`: a vertex's face count), counted at its root. */
__kernel void piece_vertices(__global const int *used, __global const int *label, __global int *count)
{
    const int v = get_global_id(0);
    if (used[v] > 0) atomic_inc(&count[label[v]]);
}
