/* OpenCL C twins of the Warp kernels that price a decimation pass's edges: quadrics.py, costs.py and guards.py
 * (read their docstrings for what each does and why); claims.cl has the claims and the collapses. Host side:
 * engine.decimation.phases, the kernels named in engine.decimation.kernel_specs.
 *
 * The same arithmetic in the same order as the Warp kernels on the CPU (which fuse no multiply-adds): dot, cross,
 * length, determinant and inverse are written out as Warp's native code computes them (warp/native/vec.h, mat.h),
 * never OpenCL's builtins (which may fuse or reorder). Layouts: vec3 arrays are packed float triples, vec3i packed
 * int triples, a quadric 10 doubles, the origin a struct of 3 doubles. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#include "pass.cl"   /* FREE, BORDER, face, has_vertex, next_of, HIST_SHIFT, mix32, listed, edge_ends */
#include "linalg.cl" /* origin_t, d3, dot3, cross3, dmin, dmax, det3, solve3 */

#define NO_KEY 0x7FFFFFFF
#define QUALITY_MIN 1.0e-3
#define QUALITY_SOFT 0.3

typedef struct {
    double q[10];
} quadric;

/* ---- vectors as Warp computes them ------------------------------------------------------------------------- */
static double len_sq(const double3 a) { return a.x * a.x + a.y * a.y + a.z * a.z; }
static double len3(const double3 a) { return sqrt(a.x * a.x + a.y * a.y + a.z * a.z); }

static double3 lcl(__global const float *pos, const int v, const origin_t o)
{
    return d3((double)pos[3 * v] - o.x, (double)pos[3 * v + 1] - o.y, (double)pos[3 * v + 2] - o.z);
}

static double3 lcl_f(const float3 p, const origin_t o) { return d3((double)p.x - o.x, (double)p.y - o.y, (double)p.z - o.z); }

/* ---- quadrics ------------------------------------------------------------------------------------------------ */
static quadric q_load(__global const double *quad, const int v)
{
    quadric q;
    for (int k = 0; k < 10; k++) q.q[k] = quad[10 * v + k];
    return q;
}

static quadric q_sum(__global const double *quad, const int a, const int b)
{
    quadric q;
    for (int k = 0; k < 10; k++) q.q[k] = quad[10 * a + k] + quad[10 * b + k];
    return q;
}

static double q_eval(const quadric *Q, const double3 p)
{
    const double *q = Q->q;
    const double x = p.x, y = p.y, z = p.z, two = 2.0;
    return q[0] * x * x + two * q[1] * x * y + two * q[2] * x * z + two * q[3] * x + q[4] * y * y +
           two * q[5] * y * z + two * q[6] * y + q[7] * z * z + two * q[8] * z + q[9];
}

/* Area-weighted quadric of the plane through a, b, c, added to acc (nothing for a degenerate face). */
static void add_plane_quadric(double *acc, const double3 a, const double3 b, const double3 c)
{
    const double3 n = cross3(b - a, c - a);
    const double length = len3(n);
    double e[10] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
    if (length > 0.0) {
        const double3 u = d3(n.x / length, n.y / length, n.z / length);
        const double d = -dot3(u, a);
        const double w = 0.5 * length;
        e[0] = w * (u.x * u.x); e[1] = w * (u.x * u.y); e[2] = w * (u.x * u.z); e[3] = w * (u.x * d);
        e[4] = w * (u.y * u.y); e[5] = w * (u.y * u.z); e[6] = w * (u.y * d);
        e[7] = w * (u.z * u.z); e[8] = w * (u.z * d);
        e[9] = w * (d * d);
    }
    for (int k = 0; k < 10; k++) acc[k] = acc[k] + e[k];
}

__kernel void vertex_quadrics(__global const float *pos, __global const int *faces, __global const int *offset,
                              __global const int *count, __global const int *star, const origin_t origin,
                              __global double *quad)
{
    const int v = get_global_id(0);
    double q[10] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
    const int lo = offset[v];
    for (int i = 0; i < count[v]; i++) {
        const int3 t = face(faces, star[lo + i]);
        add_plane_quadric(q, lcl(pos, t.x, origin), lcl(pos, t.y, origin), lcl(pos, t.z, origin));
    }
    for (int k = 0; k < 10; k++) quad[10 * v + k] = q[k];
}

/* ---- costs --------------------------------------------------------------------------------------------------- */
static int cost_code(const double cost)
{
    int c = 0;
    if (cost > 1.0e-30) {
        double x = (log2(cost) + 110.0) * 4194304.0;
        x = dmin(dmax(0.0, x), 2147483000.0);
        c = (int)x + 1;
    }
    return c;
}

static double3 placement(const quadric *Q, const double3 pa, const double3 pb)
{
    const double *q = Q->q;
    const double m[9] = {q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7]};
    const double scale = (q[0] + q[4] + q[7]) / 3.0;
    const double det = det3(m);
    const double3 mid = d3(0.5 * (pa.x + pb.x), 0.5 * (pa.y + pb.y), 0.5 * (pa.z + pb.z));
    double3 best = mid;
    int found = 0;
    if (scale > 0.0 && fabs(det) > 1.0e-9 * scale * scale * scale) {
        const double3 x = solve3(m, det, d3(q[3], q[6], q[8]));
        if (len_sq(x - mid) <= len_sq(pb - pa)) {
            best = x;
            found = 1;
        }
    }
    if (!found) {
        const double ca = q_eval(Q, pa), cb = q_eval(Q, pb), cm = q_eval(Q, mid);
        if (ca < cm && ca <= cb) best = pa;
        else if (cb < cm) best = pb;
    }
    return best;
}

/* (s, r): r, the removed vertex, is always FREE; (-1, -1) when the classes forbid the collapse. */
static int2 survivor_of(const int a, const int b, const int sa, const int sb)
{
    if (!((sa == FREE && (sb == FREE || sb == BORDER)) || (sa == BORDER && sb == FREE))) return (int2)(-1, -1);
    if (sb == BORDER) return (int2)(b, a);
    return (int2)(a, b);
}

static double collapse_cost(const quadric *Q, const double3 p, const double3 pa, const double3 pb)
{
    const double length_sq = len_sq(pb - pa);
    return dmax(q_eval(Q, p), 0.0) + 1.0e-8 * length_sq * length_sq;
}

__kernel void edge_costs(__global const float *pos, __global const int *faces, __global const int *count,
                         __global const int *state, __global const double *quad, const origin_t origin,
                         __global const int *dirty, __global int *key, __global float *target, __global int *checked)
{
    const int h = get_global_id(0);
    const int f = h / 3;
    const int k = h - 3 * f;
    if (faces[3 * f] < 0) {
        key[h] = NO_KEY;
        return;
    }
    const int a = faces[3 * f + k];
    const int b = faces[3 * f + (k + 1) % 3];
    if (a > b) {
        key[h] = NO_KEY;
        return;
    }
    if (dirty[a] == 0 && dirty[b] == 0) return;
    key[h] = NO_KEY;
    checked[h] = 0;
    const int sa = state[a], sb = state[b];
    const int2 sr = survivor_of(a, b, sa, sb);
    if (sr.x < 0) return;
    if (sa == FREE && sb == FREE && count[a] + count[b] - 4 < 3) return;
    const double3 pa = lcl(pos, a, origin);
    const double3 pb = lcl(pos, b, origin);
    const quadric q = q_sum(quad, a, b);
    double3 p = lcl(pos, sr.x, origin);
    if (sa == FREE && sb == FREE) p = placement(&q, pa, pb);
    key[h] = cost_code(collapse_cost(&q, p, pa, pb));
    vstore3((float3)((float)(p.x + origin.x), (float)(p.y + origin.y), (float)(p.z + origin.z)), h, target);
}

static bool below_cut(const int c, const int h, const int bin_below, const long frac_bits)
{
    const int b = c >> HIST_SHIFT;
    return c != NO_KEY && (b < bin_below || (b == bin_below && mix32(h) < frac_bits));
}

__kernel void cost_histogram(__global const int *key, __global int *hist)
{
    const int c = key[get_global_id(0)];
    if (c != NO_KEY) atomic_inc(&hist[c >> HIST_SHIFT]);
}

__kernel void select_candidates(__global const int *key, const int bin_below, const long frac_bits,
                                __global int *cand, __global int *listing, __global int *n_listed)
{
    const int h = get_global_id(0);
    cand[h] = 0;
    if (below_cut(key[h], h, bin_below, frac_bits)) {
        cand[h] = 1;
        listing[atomic_inc(&n_listed[0])] = h;
    }
}

/* ---- guards -------------------------------------------------------------------------------------------------- */
static double quality(const double3 a, const double3 b, const double3 c)
{
    const double s = len_sq(b - a) + len_sq(c - b) + len_sq(a - c);
    double q = 0.0;
    if (s > 0.0) q = 3.4641016151377544 * len3(cross3(b - a, c - a)) / s;
    return q;
}

static double star_turns(__global const float *pos, __global const int *faces, __global const int *star,
                         const int lo, const int n, const int moved, const int other, const double3 p,
                         const origin_t origin, const double cos_max)
{
    double worst = 1.0;
    for (int i = 0; i < n; i++) {
        const int3 t = face(faces, star[lo + i]);
        if (has_vertex(t, other)) continue;
        double3 a = lcl(pos, t.x, origin), b = lcl(pos, t.y, origin), c = lcl(pos, t.z, origin);
        const double3 n_old = cross3(b - a, c - a);
        const double q_old = quality(a, b, c);
        if (t.x == moved) a = p;
        else if (t.y == moved) b = p;
        else c = p;
        const double3 n_new = cross3(b - a, c - a);
        const double q_new = quality(a, b, c);
        const double lo_n = len3(n_old), ln_n = len3(n_new);
        if (ln_n <= 0.0) return -1.0;
        if (lo_n > 0.0 && dot3(n_old, n_new) < cos_max * lo_n * ln_n) return -1.0;
        if (q_new < QUALITY_MIN && q_new < q_old) return -1.0;
        worst = dmin(worst, q_new);
    }
    return worst;
}

static bool adjacent(__global const int *faces, __global const int *star, const int lo, const int n, const int w)
{
    for (int i = 0; i < n; i++)
        if (has_vertex(face(faces, star[lo + i]), w)) return true;
    return false;
}

__kernel void check_candidates(__global const int *listing, __global const int *n_listed, __global int *cand,
                               __global const float *pos, __global const int *faces, __global const int *offset,
                               __global const int *count, __global const int *star, __global const int *state,
                               __global const double *quad, const origin_t origin, const double cos_max,
                               const int bin_below, const long frac_bits, __global int *key, __global float *target,
                               __global int *checked)
{
    const int h = listed(listing, n_listed, cand, 1, get_global_id(0));
    if (h < 0 || checked[h] != 0) return;
    checked[h] = 1;
    const int2 ends = edge_ends(faces, h);
    const int a = ends.x, b = ends.y;
    const int sa = state[a], sb = state[b];
    const int2 sr = survivor_of(a, b, sa, sb);
    const int s = sr.x, r = sr.y;
    const int lo_r = offset[r], n_r = count[r], lo_s = offset[s], n_s = count[s];
    bool ok = true;
    int common = 0; /* link condition */
    for (int i = 0; i < n_r; i++) {
        const int w = next_of(face(faces, star[lo_r + i]), r);
        if (w != s && adjacent(faces, star, lo_s, n_s, w)) common++;
    }
    if (common != 2) ok = false;
    for (int i = 0; i < n_r; i++) { /* the opposite vertices' valences */
        const int3 u = face(faces, star[lo_r + i]);
        if (ok && has_vertex(u, s)) {
            const int x = u.x + u.y + u.z - r - s;
            const int least = state[x] == BORDER ? 2 : 4;
            if (count[x] < least) ok = false;
        }
    }
    double worst = 1.0;
    const double3 p = lcl_f(vload3(h, target), origin);
    if (ok) worst = star_turns(pos, faces, star, lo_r, n_r, r, s, p, origin, cos_max);
    if (ok && worst >= 0.0 && sa == FREE && sb == FREE)
        worst = dmin(worst, star_turns(pos, faces, star, lo_s, n_s, s, r, p, origin, cos_max));
    if (!ok || worst < 0.0) {
        key[h] = NO_KEY;
        cand[h] = 0;
        return;
    }
    if (worst < QUALITY_SOFT) {
        const double3 pa = lcl(pos, a, origin), pb = lcl(pos, b, origin);
        const quadric q = q_sum(quad, a, b);
        const double cost = collapse_cost(&q, p, pa, pb) * QUALITY_SOFT / dmax(worst, QUALITY_MIN);
        const int c = cost_code(cost);
        key[h] = c;
        if (!below_cut(c, h, bin_below, frac_bits)) cand[h] = 0;
    }
}
