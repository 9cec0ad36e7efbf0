/* OpenCL C twins of the device-mesh kernels the decimation runs (the Warp kernels of
 * engine/surface/kernels/topology.py and compaction.py, and quadrics.py's scatter_kept, collapse.py's
 * lock_vertices): every vertex's star as sorted CSR, the vertex classes, compaction, the bounding box.
 * Host side: engine.decimation.meshops. Integer logic only (the bounding box is a min / max): the same result as
 * the Warp kernels whatever order the work items run in.
 *
 * A mesh is `pos` (packed float triples, z y x mm) and `faces` (packed int triples); a removed face is (-1,-1,-1).
 * Quadrics are 10 doubles per vertex. */
#pragma OPENCL FP_CONTRACT OFF

#define FREE 0
#define BORDER 1
#define LOCKED 2
#define DEAD 3

static int next_of(const int3 t, const int v)
{
    int r = t.x;
    if (t.x == v) r = t.y;
    else if (t.y == v) r = t.z;
    return r;
}

static int prev_of(const int3 t, const int v)
{
    int r = t.y;
    if (t.x == v) r = t.z;
    else if (t.y == v) r = t.x;
    return r;
}

__kernel void count_incidence(__global const int *faces, __global int *count)
{
    const int3 t = vload3(get_global_id(0), faces);
    if (t.x >= 0) {
        atomic_inc(&count[t.x]);
        atomic_inc(&count[t.y]);
        atomic_inc(&count[t.z]);
    }
}

__kernel void fill_incidence(__global const int *faces, __global const int *offset, __global int *cursor,
                             __global int *star)
{
    const int f = get_global_id(0);
    if (faces[3 * f] < 0) return;
    for (int k = 0; k < 3; k++) {
        const int v = faces[3 * f + k];
        const int slot = atomic_inc(&cursor[v]);
        star[offset[v] + slot] = f;
    }
}

/* Insertion sort of each star, so that results do not depend on the fill's atomic order. */
__kernel void sort_incidence(__global const int *offset, __global const int *count, __global int *star)
{
    const int v = get_global_id(0);
    const int lo = offset[v];
    const int n = count[v];
    for (int i = 1; i < n; i++) {
        const int x = star[lo + i];
        int j = i - 1;
        while (j >= 0 && star[lo + j] > x) {
            star[lo + j + 1] = star[lo + j];
            j--;
        }
        star[lo + j + 1] = x;
    }
}

/* FREE (one closed fan), BORDER (one open fan), LOCKED (anything else) or DEAD (no face). */
__kernel void classify_vertices(__global const int *faces, __global const int *offset, __global const int *count,
                                __global const int *star, __global int *state)
{
    const int v = get_global_id(0);
    const int n = count[v];
    if (n == 0) {
        state[v] = DEAD;
        return;
    }
    const int lo = offset[v];
    int bad = 0, open_fwd = 0, open_bwd = 0, start = 0;
    for (int i = 0; i < n; i++) {
        const int3 t = vload3(star[lo + i], faces);
        if (t.x == t.y || t.y == t.z || t.x == t.z) bad = 1;
        const int nx = next_of(t, v);
        const int pv = prev_of(t, v);
        int same_next = 0, same_prev = 0, fwd = 0, bwd = 0;
        for (int j = 0; j < n; j++) {
            const int3 u = vload3(star[lo + j], faces);
            const int nj = next_of(u, v);
            const int pj = prev_of(u, v);
            if (nj == nx) same_next++;
            if (pj == pv) same_prev++;
            if (pj == nx) fwd++;
            if (nj == pv) bwd++;
        }
        if (same_next != 1 || same_prev != 1 || fwd > 1 || bwd > 1) bad = 1;
        if (fwd == 0) open_fwd++;
        if (bwd == 0) {
            open_bwd++;
            start = i;
        }
    }
    if (bad != 0 || open_fwd > 1 || open_fwd != open_bwd) {
        state[v] = LOCKED;
        return;
    }
    int i = start, steps = 0; /* walk the fan from its start: it must visit every face (one fan only) */
    while (steps < n) {
        steps++;
        const int nx = next_of(vload3(star[lo + i], faces), v);
        int found = -1;
        for (int j = 0; j < n; j++)
            if (prev_of(vload3(star[lo + j], faces), v) == nx) found = j;
        if (found < 0 || found == start) break;
        i = found;
    }
    if (steps != n) state[v] = LOCKED;
    else if (open_fwd == 0) state[v] = FREE;
    else state[v] = BORDER;
}

__kernel void alive_flags(__global const int *faces, __global int *flag)
{
    const int f = get_global_id(0);
    flag[f] = faces[3 * f] >= 0 ? 1 : 0;
}

__kernel void scatter_faces(__global const int *faces, __global const int *slot, __global int *out)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    if (t.x >= 0) vstore3(t, slot[f], out);
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
    if (count[v] > 0) vstore3(vload3(v, pos), slot[v], out);
}

__kernel void remap_faces(__global int *faces, __global const int *slot)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    vstore3((int3)(slot[t.x], slot[t.y], slot[t.z]), f, faces);
}

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

static void atomic_fmin(volatile __global float *p, const float x)
{
    int old = as_int(*p);
    while (x < as_float(old)) {
        const int seen = atomic_cmpxchg((volatile __global int *)p, old, as_int(x));
        if (seen == old) break;
        old = seen;
    }
}

static void atomic_fmax(volatile __global float *p, const float x)
{
    int old = as_int(*p);
    while (x > as_float(old)) {
        const int seen = atomic_cmpxchg((volatile __global int *)p, old, as_int(x));
        if (seen == old) break;
        old = seen;
    }
}

/* box[0..2] = component-wise minimum, box[3..5] = maximum (compare-and-swap per component). */
__kernel void bounds_kernel(__global const float *pos, __global float *box)
{
    const int v = get_global_id(0);
    for (int k = 0; k < 3; k++) {
        atomic_fmin(&box[k], pos[3 * v + k]);
        atomic_fmax(&box[3 + k], pos[3 * v + k]);
    }
}
