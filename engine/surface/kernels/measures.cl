/* OpenCL C twins of measures.py's Warp kernels: the edge census, face volumes and areas (float64), connected pieces
 * (min-label hooking with pointer jumping), their volumes and their removal, and the run sums of a float64 array.
 * Faces are packed int triples, positions packed float triples (z, y, x); float64 as in the Warp kernels. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable

#include "common.cl" /* next_of, prev_of, has_vertex (engine/backend/kernels) */

/* a (z, y, x) float32 position as float64 (x, y, z) */
static double3 xyz64(__global const float *pos, int v)
{
    const float3 p = vload3(v, pos);
    return (double3)((double)p.z, (double)p.y, (double)p.x);
}

static double3 cross64(double3 a, double3 b)
{
    return (double3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

static double dot64(double3 a, double3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

static void atomic_add_double(volatile __global double *p, double v)
{
    union { double d; long l; } old, val;
    old.d = *p;
    while (true) {
        val.d = old.d + v;
        const long seen = atom_cmpxchg((volatile __global long *)p, old.l, val.l);
        if (seen == old.l) break;
        old.l = seen;
    }
}

__kernel void edge_census(__global const int *faces, __global const int *offset, __global const int *count,
                          __global const int *star, __global long *totals)
{
    const int v = get_global_id(0);
    const int lo = offset[v];
    const int n = count[v];
    long edges = 0, border = 0, nonmanifold = 0, inconsistent = 0;
    for (int i = 0; i < n; i++) {
        const int3 t = vload3(star[lo + i], faces);
        for (int side = 0; side < 2; side++) {
            const int w = side == 1 ? prev_of(t, v) : next_of(t, v);
            if (w <= v) continue;
            int seen = 0;
            for (int j = 0; j < i; j++) {
                if (has_vertex(vload3(star[lo + j], faces), w)) seen = 1;
            }
            if (side == 1 && next_of(t, v) == w) seen = 1;
            if (seen != 0) continue;
            int c = 0, fwd = 0;
            for (int j = 0; j < n; j++) {
                const int3 u = vload3(star[lo + j], faces);
                if (has_vertex(u, w)) {
                    c += 1;
                    if (next_of(u, v) == w) fwd += 1;
                }
            }
            edges += 1;
            if (c == 1) border += 1;
            else if (c > 2) nonmanifold += 1;
            else if (fwd != 1) inconsistent += 1;
        }
    }
    if (edges > 0) atom_add(&totals[0], edges); /* the faults' totals only where there are some */
    if (border > 0) atom_add(&totals[1], border);
    if (nonmanifold > 0) atom_add(&totals[2], nonmanifold);
    if (inconsistent > 0) atom_add(&totals[3], inconsistent);
}

__kernel void face_measures(__global const float *pos, __global const int *faces, const int first,
                            __global double *volume, __global double *area, __global double *degenerate)
{
    const int f = get_global_id(0);
    const int3 t = vload3(first + f, faces);
    const double3 a = xyz64(pos, t.x);
    const double3 b = xyz64(pos, t.y);
    const double3 c = xyz64(pos, t.z);
    volume[f] = dot64(a, cross64(b, c)) / 6.0;
    const double3 n = cross64(b - a, c - a);
    area[f] = 0.5 * sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    degenerate[f] = (t.x == t.y || t.y == t.z || t.x == t.z) ? 1.0 : 0.0;
}

/* the sum of every run [r * run, min((r + 1) * run, n)) of values, in order, into out[r] */
__kernel void run_sums(__global const double *values, const int n, const int run, __global double *out)
{
    const int r = get_global_id(0);
    const long lo = (long)r * run;
    const long hi = min(lo + run, (long)n);
    double s = 0.0;
    for (long k = lo; k < hi; k++) s = s + values[k];
    out[r] = s;
}

__kernel void hook_labels(__global const int *faces, volatile __global int *label, __global int *changed)
{
    const int f = get_global_id(0);
    const int3 t3 = vload3(f, faces);
    const int t[3] = {t3.x, t3.y, t3.z};
    const int m = min(min(label[t[0]], label[t[1]]), label[t[2]]);
    for (int k = 0; k < 3; k++) {
        const int r = label[t[k]];
        if (r > m) {
            atomic_min(&label[r], m);
            atomic_min(&label[t[k]], m);
            changed[0] = 1;
        }
    }
}

/* every vertex its own piece (made on the device: no volume-sized copy up) */
__kernel void own_labels(__global int *label)
{
    const int v = get_global_id(0);
    label[v] = v;
}

/* pointer jumping: every labelled entry's label becomes its chain's root (a negative label: none, left) */
__kernel void jump_labels(volatile __global int *label)
{
    const int v = get_global_id(0);
    int r = label[v];
    if (r < 0) return;
    while (label[r] != r) r = label[r];
    label[v] = r;
}

__kernel void count_roots(__global const int *label, __global const int *count, __global int *roots)
{
    const int v = get_global_id(0);
    if (count[v] > 0 && label[v] == v) atomic_add(&roots[0], 1);
}

/* each work item takes a run of faces and adds once per change of piece (few atomics on the big pieces' roots) */
__kernel void piece_volumes(__global const float *pos, __global const int *faces, __global const int *label,
                            const int n_faces, const int run, __global double *volume, __global int *nfaces)
{
    const int r = get_global_id(0);
    const int lo = r * run;
    const int hi = min(lo + run, n_faces);
    int cur = -1, cnt = 0;
    double acc = 0.0;
    for (int f = lo; f < hi; f++) {
        const int3 t = vload3(f, faces);
        const int root = label[t.x];
        if (root != cur) {
            if (cur >= 0) {
                atomic_add_double(&volume[cur], acc);
                atomic_add(&nfaces[cur], cnt);
            }
            cur = root;
            acc = 0.0;
            cnt = 0;
        }
        acc = acc + dot64(xyz64(pos, t.x), cross64(xyz64(pos, t.y), xyz64(pos, t.z))) / 6.0;
        cnt = cnt + 1;
    }
    if (cur >= 0) {
        atomic_add_double(&volume[cur], acc);
        atomic_add(&nfaces[cur], cnt);
    }
}

__kernel void drop_pieces(__global int *faces, __global const int *label, __global const int *keep)
{
    const int f = get_global_id(0);
    if (keep[label[faces[3 * (long)f]]] == 0) {
        for (int k = 0; k < 3; k++) faces[3 * (long)f + k] = -1;
    }
}
