/* OpenCL C twins of tiles.py's Warp kernels: decimating a mesh piece by piece (groups of slabs, seams, z tiles;
 * read that file's docstrings). Host side: engine.decimation.pieces, tiles, groups, seams. Integer bookkeeping,
 * quadric additions (one per element, in the same order as Warp) and float comparisons only. Layouts: vec3 arrays
 * are packed float triples, vec3i packed int triples, a quadric 10 doubles. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

__kernel void localize_faces(__global int *faces, const int v0, const int n_foreign, const int fmin,
                             __global const int *fmap)
{
    const int f = get_global_id(0);
    for (int k = 0; k < 3; k++) {
        const int v = faces[3 * f + k];
        faces[3 * f + k] = v >= v0 ? v - v0 + n_foreign : fmap[v - fmin];
    }
}

__kernel void globalize_faces(__global int *faces, const int n_foreign, __global const int *foreign_out,
                              const int base)
{
    const int f = get_global_id(0);
    for (int k = 0; k < 3; k++) {
        const int v = faces[3 * f + k];
        faces[3 * f + k] = v < n_foreign ? foreign_out[v] : v + base;
    }
}

__kernel void add_quadrics(__global const int *ids, __global const double *shares, __global double *quad)
{
    const int i = get_global_id(0);
    const int v = ids[i];
    for (int k = 0; k < 10; k++) quad[10 * v + k] = quad[10 * v + k] + shares[10 * i + k];
}

__kernel void seam_flags(__global const float *pos, __global const int *faces, __global const float *borders,
                         const int n_borders, const float width, __global int *flag)
{
    const int f = get_global_id(0);
    const float z = pos[3 * faces[3 * f]];
    int near = 0;
    for (int i = 0; i < n_borders; i++)
        if (fabs(z - borders[i]) <= width) near = 1;
    flag[f] = near;
}

__kernel void range_flags(__global const float *pos, __global const int *faces, const int axis, const float lo,
                          const float hi, __global int *flag)
{
    const int f = get_global_id(0);
    const float c = pos[3 * faces[3 * f] + axis];
    flag[f] = (c >= lo && c < hi) ? 1 : 0;
}

__kernel void face_sample(__global const float *pos, __global const int *faces, const int stride, __global float *out)
{
    const int i = get_global_id(0);
    vstore3(vload3(faces[3 * (i * stride)], pos), i, out);
}

__kernel void mark_used(__global const int *faces, __global const int *flag, const int want, __global int *used)
{
    const int f = get_global_id(0);
    if (flag[f] == want) {
        used[faces[3 * f]] = 1;
        used[faces[3 * f + 1]] = 1;
        used[faces[3 * f + 2]] = 1;
    }
}

__kernel void split_faces(__global const int *faces, __global const int *flag, __global const int *slot,
                          __global const int *vslot, __global int *seam, __global int *rest)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    if (flag[f] == 1) vstore3((int3)(vslot[t.x], vslot[t.y], vslot[t.z]), slot[f], seam);
    else vstore3(t, f - slot[f], rest);
}

__kernel void gather_seam(__global const float *pos, __global const int *in_seam, __global const int *in_rest,
                          __global const int *vslot, __global int *vids, __global float *local_pos,
                          __global int *lock)
{
    const int v = get_global_id(0);
    if (in_seam[v] != 0) {
        const int i = vslot[v];
        vids[i] = v;
        vstore3(vload3(v, pos), i, local_pos);
        lock[i] = in_rest[v];
    }
}

__kernel void new_vertex_flags(__global const int *kept, __global const int *lock, __global int *flag)
{
    const int i = get_global_id(0);
    flag[i] = 1 - min(lock[kept[i]], 1);
}

__kernel void join_seam(__global const float *out_pos, __global const int *kept, __global const int *lock,
                        __global const int *vids, __global const int *new_slot, const int n_old, __global int *out_id,
                        __global float *new_pos)
{
    const int i = get_global_id(0);
    const int k = kept[i];
    if (lock[k] != 0) {
        out_id[i] = vids[k];
    } else {
        out_id[i] = n_old + new_slot[i];
        vstore3(vload3(i, out_pos), new_slot[i], new_pos);
    }
}
