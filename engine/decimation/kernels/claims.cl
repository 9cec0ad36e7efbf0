/* OpenCL C twins of the Warp kernels of a decimation pass's claims and collapses: claims.py and collapse.py (read
 * their docstrings); price.cl prices the edges. Host side: engine.decimation.phases. Integer logic and 64-bit
 * atomics (cl_khr_int64_extended_atomics): the winners do not depend on the order work items run in. mix32,
 * listed and edge_ends are in pass.cl (price.cl includes it too). Layouts: vec3 arrays are packed float triples,
 * vec3i packed int triples, a quadric 10 doubles. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable

#include "pass.cl" /* FREE, BORDER, DEAD, face, has_vertex, HIST_SHIFT, mix32, listed, edge_ends */

#define CLAIM_FREE 0x7FFFFFFFFFFFFFFFL
#define CLAIM_TAKEN (-1L)
#define TRIMMED 5

/* ---- claims -------------------------------------------------------------------------------------------------- */
static long priority(const int code, const int h) { return ((long)code << 32) | mix32(h); }

__kernel void claim_stars(__global const int *listing, __global const int *n_listed, __global const int *cand,
                          __global const int *key, __global const int *faces, __global const int *offset,
                          __global const int *count, __global const int *star, __global long *claim)
{
    const int h = listed(listing, n_listed, cand, 1, get_global_id(0));
    if (h < 0) return;
    const long mine = priority(key[h], h);
    const int2 ends = edge_ends(faces, h);
    for (int e = 0; e < 2; e++) {
        const int v = e == 0 ? ends.x : ends.y;
        const int lo = offset[v];
        for (int i = 0; i < count[v]; i++) atom_min(&claim[star[lo + i]], mine);
    }
}

__kernel void settle_claims(__global const int *listing, __global const int *n_listed, __global int *cand,
                            __global const int *key, __global const int *faces, __global const int *offset,
                            __global const int *count, __global const int *star, __global const long *claim,
                            __global int *winners)
{
    const int h = listed(listing, n_listed, cand, 1, get_global_id(0));
    if (h < 0) return;
    const long mine = priority(key[h], h);
    const int2 ends = edge_ends(faces, h);
    int won = 1;
    for (int e = 0; e < 2; e++) {
        const int v = e == 0 ? ends.x : ends.y;
        const int lo = offset[v];
        for (int i = 0; i < count[v]; i++) {
            const long c = claim[star[lo + i]];
            if (c == CLAIM_TAKEN) won = -1;
            else if (c != mine && won == 1) won = 0;
        }
    }
    if (won == 1) {
        cand[h] = 3;
        atomic_inc(&winners[0]);
    } else if (won == -1) {
        cand[h] = 0;
    }
}

__kernel void take_stars(__global const int *listing, __global const int *n_listed, __global int *cand,
                         __global const int *faces, __global const int *offset, __global const int *count,
                         __global const int *star, __global long *claim)
{
    const int h = listed(listing, n_listed, cand, 3, get_global_id(0));
    if (h < 0) return;
    cand[h] = 2;
    const int2 ends = edge_ends(faces, h);
    for (int e = 0; e < 2; e++) {
        const int v = e == 0 ? ends.x : ends.y;
        const int lo = offset[v];
        for (int i = 0; i < count[v]; i++) claim[star[lo + i]] = CLAIM_TAKEN;
    }
}

__kernel void release_claims(__global long *claim)
{
    const int i = get_global_id(0);
    if (claim[i] != CLAIM_TAKEN) claim[i] = CLAIM_FREE;
}

__kernel void winner_histogram(__global const int *listing, __global const int *n_listed, __global const int *cand,
                               __global const int *key, __global int *hist)
{
    const int h = listed(listing, n_listed, cand, 2, get_global_id(0));
    if (h >= 0) atomic_inc(&hist[key[h] >> HIST_SHIFT]);
}

__kernel void trim_winners(__global const int *listing, __global const int *n_listed, __global int *cand,
                           __global const int *key, const int bin_below, const long frac_bits, const int salt)
{
    const int h = listed(listing, n_listed, cand, 2, get_global_id(0));
    if (h < 0) return;
    const int b = key[h] >> HIST_SHIFT;
    if (b > bin_below || (b == bin_below && mix32(h ^ salt) >= frac_bits)) cand[h] = TRIMMED;
}

__kernel void cheapest_trimmed(__global const int *listing, __global const int *n_listed, __global const int *cand,
                               __global const int *key, __global long *best)
{
    const int h = listed(listing, n_listed, cand, TRIMMED, get_global_id(0));
    if (h >= 0) atom_min(&best[0], priority(key[h], h));
}

__kernel void restore_cheapest(__global const int *listing, __global const int *n_listed, __global int *cand,
                               __global const int *key, __global const long *best)
{
    const int h = listed(listing, n_listed, cand, TRIMMED, get_global_id(0));
    if (h >= 0 && priority(key[h], h) == best[0]) cand[h] = 2;
}

/* ---- collapse ------------------------------------------------------------------------------------------------ */
__kernel void apply_collapses(__global const int *listing, __global const int *n_listed, __global const int *cand,
                              __global const float *target, __global int *faces, __global const int *offset,
                              __global const int *count, __global const int *star, __global int *state,
                              __global double *quad, __global float *pos, __global int *removed_faces,
                              __global int *dirty)
{
    const int h = listed(listing, n_listed, cand, 2, get_global_id(0));
    if (h < 0) return;
    const int2 ends = edge_ends(faces, h);
    const int a = ends.x, b = ends.y;
    int s = a, r = b;
    if (state[b] == BORDER) {
        s = b;
        r = a;
    }
    if (state[a] == FREE && state[b] == FREE) vstore3(vload3(h, target), s, pos);
    for (int k = 0; k < 10; k++) quad[10 * s + k] = quad[10 * s + k] + quad[10 * r + k];
    state[r] = DEAD;
    int opposite[2] = {-1, -1};
    int n_opp = 0;
    const int lo = offset[r];
    for (int i = 0; i < count[r]; i++) {
        const int fi = star[lo + i];
        int3 u = face(faces, fi);
        if (has_vertex(u, s)) {
            if (n_opp < 2) opposite[n_opp] = u.x + u.y + u.z - r - s;
            n_opp++;
            vstore3((int3)(-1, -1, -1), fi, faces);
            atomic_inc(&removed_faces[0]);
        } else {
            if (u.x == r) u.x = s;
            if (u.y == r) u.y = s;
            if (u.z == r) u.z = s;
            vstore3(u, fi, faces);
        }
    }
    for (int e = 0; e < 4; e++) {
        const int c = e == 0 ? a : (e == 1 ? b : opposite[e - 2]);
        if (c < 0) continue;
        for (int i = 0; i < count[c]; i++) {
            const int fi = star[offset[c] + i];
            for (int j = 0; j < 3; j++) {
                const int w = faces[3 * fi + j];
                if (w >= 0) dirty[w] = 1;
            }
        }
    }
}
