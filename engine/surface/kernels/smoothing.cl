/* OpenCL C twins of smoothing.py's Warp kernels: vertex normals and surface-preserving Laplacian smoothing, the same
 * float32 arithmetic in the same order (no fused multiply-adds; products and sums written out, no built-in dot or
 * cross). Positions are packed float triples (z, y, x) read with vload3, faces packed int triples; face normals are
 * taken with vertices in (x, y, z) order (the (z, y, x) cross product negated). */
#pragma OPENCL FP_CONTRACT OFF

/* area-weighted normal (twice the area) of triangle a, b, c, oriented for (x, y, z) order, in (z, y, x) */
static float3 face_normal_zyx(float3 a, float3 b, float3 c)
{
    const float3 u = b - a;
    const float3 w = c - a;
    return (float3)(-(u.y * w.z - u.z * w.y), -(u.z * w.x - u.x * w.z), -(u.x * w.y - u.y * w.x));
}

static float dot3(float3 a, float3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

static float length3(float3 a) { return sqrt(a.x * a.x + a.y * a.y + a.z * a.z); }

static bool turns_too_far(float3 n_old, float3 n_new, float cos_max)
{
    const float lo = length3(n_old);
    const float ln = length3(n_new);
    bool bad = true;
    if (lo > 0.0f && ln > 0.0f) bad = dot3(n_old, n_new) < cos_max * lo * ln;
    return bad;
}

__kernel void star_neighbour_mean(__global const float *pos, __global const int *faces, __global const int *offset,
                                  __global const int *count, __global const int *star, __global float *cand)
{
    const int v = get_global_id(0);
    const int lo = offset[v];
    const int n = count[v];
    float3 acc = (float3)(0.0f, 0.0f, 0.0f);
    float3 p = vload3(v, pos);
    for (int i = 0; i < n; i++) {
        const int3 t = vload3(star[lo + i], faces);
        acc = acc + vload3(t.x, pos) + vload3(t.y, pos) + vload3(t.z, pos) - p;
    }
    if (n > 0) p = acc / (float)(2 * n);
    vstore3(p, v, cand);
}

__kernel void star_normals(__global const float *pos, __global const int *faces, __global const int *offset,
                           __global const int *count, __global const int *star, __global float *out)
{
    const int v = get_global_id(0);
    const int lo = offset[v];
    const int n = count[v];
    float3 acc = (float3)(0.0f, 0.0f, 0.0f);
    for (int i = 0; i < n; i++) {
        const int3 t = vload3(star[lo + i], faces);
        acc = acc + face_normal_zyx(vload3(t.x, pos), vload3(t.y, pos), vload3(t.z, pos));
    }
    const float length = length3(acc);
    if (length > 0.0f) acc = acc / length;
    vstore3(acc, v, out);
}

__kernel void fixed_from_classes(__global const int *state, __global int *fixed)
{
    const int i = get_global_id(0);
    fixed[i] = state[i] != 0 ? 1 : 0;
}

__kernel void reject_moves(__global const float *pos, __global const float *cand, __global const int *faces,
                           const float cos_max, __global int *reject)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    const float3 a = vload3(t.x, pos);
    const float3 b = vload3(t.y, pos);
    const float3 c = vload3(t.z, pos);
    const float3 n_old = face_normal_zyx(a, b, c);
    if (turns_too_far(n_old, face_normal_zyx(vload3(t.x, cand), b, c), cos_max)) reject[t.x] = 1;
    if (turns_too_far(n_old, face_normal_zyx(a, vload3(t.y, cand), c), cos_max)) reject[t.y] = 1;
    if (turns_too_far(n_old, face_normal_zyx(a, b, vload3(t.z, cand)), cos_max)) reject[t.z] = 1;
}

__kernel void accept_moves(__global const float *pos, __global float *cand, __global const int *reject,
                           __global const int *fixed, __global int *moved)
{
    const int i = get_global_id(0);
    if (reject[i] == 0 && fixed[i] == 0) atomic_add(&moved[0], 1);
    else vstore3(vload3(i, pos), i, cand);
}

__kernel void find_violations(__global const float *old, __global const float *pos, __global const int *faces,
                              const float cos_max, __global int *revert, __global int *count)
{
    const int f = get_global_id(0);
    const int3 t = vload3(f, faces);
    const float3 n_old = face_normal_zyx(vload3(t.x, old), vload3(t.y, old), vload3(t.z, old));
    const float3 n_new = face_normal_zyx(vload3(t.x, pos), vload3(t.y, pos), vload3(t.z, pos));
    if (turns_too_far(n_old, n_new, cos_max)) {
        const int ts[3] = {t.x, t.y, t.z};
        for (int k = 0; k < 3; k++) {
            const float3 d = vload3(ts[k], pos) - vload3(ts[k], old);
            if (d.x * d.x + d.y * d.y + d.z * d.z > 0.0f) {
                revert[ts[k]] = 1;
                atomic_add(&count[0], 1);
            }
        }
    }
}

__kernel void revert_moves(__global const float *old, __global float *pos, __global int *revert)
{
    const int i = get_global_id(0);
    if (revert[i] != 0) {
        vstore3(vload3(i, old), i, pos);
        revert[i] = 0;
    }
}
