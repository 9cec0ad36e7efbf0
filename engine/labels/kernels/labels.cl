/* OpenCL C twins of labels.py's Warp kernels (the per-label meshing): the same names, arguments and arithmetic in
 * the same order. VOL_T is the label map's integer type (built once per type by engine.backend.opencl_backend).
 * A Warp kernel over dim (a, b, c) runs over the global size (c, b, a): id 0 is the fastest axis. Positions and
 * faces are packed triples (z, y, x); 2-D tables are rows of ints. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable

#define CROP_COLS 7 /* atlas z0, grid z0, y0, x0, dy, dx, value */

__kernel void mark_extent(__global const VOL_T *labels, __global const int *lut, const int n_lut, __global int *fz,
                          __global int *fy, __global int *fx, const int nz, const int ny, const int nx)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const long v = (long)labels[((long)z * ny + y) * nx + x];
    if (v <= 0 || v >= n_lut) return;
    const int s = lut[v];
    if (s < 0) return;
    if (fz[(long)s * nz + z] == 0) fz[(long)s * nz + z] = 1;
    if (fy[(long)s * ny + y] == 0) fy[(long)s * ny + y] = 1;
    if (fx[(long)s * nx + x] == 0) fx[(long)s * nx + x] = 1;
}

__kernel void fill_atlas(__global const VOL_T *labels, __global const int *plane_crop, __global const int *crops,
                         const float other, __global float *out, const int nz, const int ny, const int nx)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const int ax = (int)get_global_size(0);
    const int ay = (int)get_global_size(1);
    __global const int *c = crops + (long)plane_crop[z] * CROP_COLS;
    float val = 0.0f;
    if (y < c[4] && x < c[5]) {
        const int gz = c[1] + z - c[0];
        const int gy = c[2] + y;
        const int gx = c[3] + x;
        if (gz >= 0 && gy >= 0 && gx >= 0 && gz < nz && gy < ny && gx < nx) {
            const long v = (long)labels[((long)gz * ny + gy) * nx + gx];
            if (v == c[6]) val = 1.0f;
            else if (v != 0) val = other;
        }
    }
    out[((long)z * ay + y) * ax + x] = val;
}

__kernel void place_vertices(__global const float *pos, __global const int *plane_crop, const int n_planes,
                             __global const int *crops, __global const int *crop_slot, __global const VOL_T *labels,
                             const float sz, const float sy, const float sx, const int first, __global float *out_pos,
                             __global int *slot, __global int *near, const int nz, const int ny, const int nx)
{
    const int i = (int)get_global_id(0);
    const float3 p = vload3(i, pos);
    int plane = (int)floor(p.x / sz + 0.5f);
    plane = clamp(plane, 0, n_planes - 1);
    const int ci = plane_crop[plane];
    __global const int *c = crops + (long)ci * CROP_COLS;
    const float3 g = (float3)(p.x + (float)(c[1] - c[0]) * sz, p.y + (float)c[2] * sy, p.z + (float)c[3] * sx);
    vstore3(g, first + i, out_pos);
    slot[first + i] = crop_slot[ci];
    const int bz = (int)floor(g.x / sz);
    const int by = (int)floor(g.y / sy);
    const int bx = (int)floor(g.z / sx);
    const long own = c[6];
    int flag = 0;
    for (int dz = 0; dz < 2; dz++)
        for (int dy = 0; dy < 2; dy++)
            for (int dx = 0; dx < 2; dx++) {
                const int z = bz + dz;
                const int y = by + dy;
                const int x = bx + dx;
                if (z >= 0 && y >= 0 && x >= 0 && z < nz && y < ny && x < nx) {
                    const long v = (long)labels[((long)z * ny + y) * nx + x];
                    if (v != 0 && v != own) flag = 1;
                }
            }
    near[first + i] = flag;
}

__kernel void offset_faces(__global const int *faces, const int offset, const int first, __global int *out)
{
    const int i = (int)get_global_id(0);
    vstore3(vload3(i, faces) + offset, first + i, out);
}

__kernel void gather_slots(__global const int *slot, __global const int *kept, __global int *out)
{
    const int i = (int)get_global_id(0);
    out[i] = slot[kept[i]];
}

__kernel void face_sums(__global const float *pos, __global const int *faces, __global const int *slot,
                        const float scale, __global int *count, __global long *area)
{
    const int i = (int)get_global_id(0);
    const int3 f = vload3(i, faces);
    const int s = slot[f.x];
    const float3 a = vload3(f.x, pos);
    const float3 b = vload3(f.y, pos);
    const float3 c = vload3(f.z, pos);
    const float3 e0 = (float3)(b.x - a.x, b.y - a.y, b.z - a.z);
    const float3 e1 = (float3)(c.x - a.x, c.y - a.y, c.z - a.z);
    const float cz = e0.y * e1.z - e0.z * e1.y;
    const float cy = e0.z * e1.x - e0.x * e1.z;
    const float cx = e0.x * e1.y - e0.y * e1.x;
    const float sq = cz * cz + cy * cy + cx * cx;
    const float tri = 0.5f * sqrt(sq);
    atomic_add(count + s, 1);
    atom_add(area + s, (long)(tri * scale + 0.5f));
}

__kernel void lock_slots(__global const int *slot, __global const int *open_slot, __global const int *near,
                         __global int *locked)
{
    const int i = (int)get_global_id(0);
    locked[i] = max(near[i], 1 - open_slot[slot[i]]);
}
