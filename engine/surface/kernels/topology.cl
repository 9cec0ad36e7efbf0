/* OpenCL C twins of topology.py's Warp kernels: every vertex's star (the faces around it) as sorted CSR, and each
 * vertex's class. Faces are packed int triples (a removed face is -1, -1, -1); the same logic, in the same order,
 * as the Warp kernels. */
#pragma OPENCL FP_CONTRACT OFF

#include "common.cl" /* FREE, BORDER, LOCKED, DEAD; next_of, prev_of (engine/backend/kernels) */

__kernel void count_incidence(__global const int *faces, __global int *count)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    if (t.x >= 0) {
        atomic_add(&count[t.x], 1);
        atomic_add(&count[t.y], 1);
        atomic_add(&count[t.z], 1);
    }
}

__kernel void fill_incidence(__global const int *faces, __global const int *offset, __global int *cursor,
                             __global int *star)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    if (t.x >= 0) {
        star[offset[t.x] + atomic_add(&cursor[t.x], 1)] = f;
        star[offset[t.y] + atomic_add(&cursor[t.y], 1)] = f;
        star[offset[t.z] + atomic_add(&cursor[t.z], 1)] = f;
    }
}

__kernel void sort_incidence(__global const int *offset, __global const int *count, __global int *star)
{
    const int v = get_global_id(0);
    const int lo = offset[v];
    const int n = count[v];
    for (int i = 1; i < n; i++) {
        const int x = star[lo + i];
        int j = i - 1;
        while (j >= 0) {
            const int y = star[lo + j];
            if (y > x) {
                star[lo + j + 1] = y;
                j -= 1;
            } else {
                break;
            }
        }
        star[lo + j + 1] = x;
    }
}

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
            if (nj == nx) same_next += 1;
            if (pj == pv) same_prev += 1;
            if (pj == nx) fwd += 1;
            if (nj == pv) bwd += 1;
        }
        if (same_next != 1 || same_prev != 1 || fwd > 1 || bwd > 1) bad = 1;
        if (fwd == 0) open_fwd += 1;
        if (bwd == 0) {
            open_bwd += 1;
            start = i;
        }
    }
    if (bad != 0 || open_fwd > 1 || open_fwd != open_bwd) {
        state[v] = LOCKED;
        return;
    }
    /* walk the fan from its start: it must visit every face (one fan only) */
    int i = start, steps = 0;
    while (steps < n) {
        steps += 1;
        const int nx = next_of(vload3(star[lo + i], faces), v);
        int found = -1;
        for (int j = 0; j < n; j++) {
            if (prev_of(vload3(star[lo + j], faces), v) == nx) found = j;
        }
        if (found < 0 || found == start) break;
        i = found;
    }
    if (steps != n) state[v] = LOCKED;
    else if (open_fwd == 0) state[v] = FREE;
    else state[v] = BORDER;
}

__kernel void count_classes(__global const int *state, __global int *counts)
{
    const int c = state[get_global_id(0)];
    if (c != FREE) atomic_inc(&counts[c]); /* FREE's count is the rest (the host's) */
}
