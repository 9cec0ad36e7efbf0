/* OpenCL C twins of layout.py's Warp kernels: the patient frame, the STL's facet records and the glTF buffers, the
 * same arithmetic in the same order (float64 where the Warp kernels use it, no fused multiply-adds). Positions and
 * vectors are packed float triples (z, y, x), faces packed int triples; ``m`` is the 3 x 3 map (row-major, on
 * (x, y, z)) followed by the offset, 12 doubles. */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

static void xyz64(__global const float *a, int i, double *p)
{
    p[0] = (double)a[3 * (long)i + 2];
    p[1] = (double)a[3 * (long)i + 1];
    p[2] = (double)a[3 * (long)i];
}

/* m @ p, then + the offset where ``shift``; stored (z, y, x) float32 */
static void map_store(__global const double *m, const double *p, bool shift, __global float *out, int v)
{
    for (int i = 0; i < 3; i++) {
        double r = m[3 * i] * p[0];
        r = r + m[3 * i + 1] * p[1];
        r = r + m[3 * i + 2] * p[2];
        if (shift) r = r + m[9 + i];
        out[3 * (long)v + 2 - i] = (float)r;
    }
}

__kernel void affine_points(__global const float *pos, __global const double *m, __global float *out)
{
    const int v = get_global_id(0);
    double p[3];
    xyz64(pos, v, p);
    map_store(m, p, true, out, v);
}

__kernel void rotate_vectors(__global const float *vec, __global const double *m, __global float *out)
{
    const int v = get_global_id(0);
    double p[3];
    xyz64(vec, v, p);
    map_store(m, p, false, out, v);
}

__kernel void reverse_faces(__global const int *faces, __global int *out)
{
    const long f = get_global_id(0);
    out[3 * f] = faces[3 * f + 2];
    out[3 * f + 1] = faces[3 * f + 1];
    out[3 * f + 2] = faces[3 * f];
}

static double3 xyz64v(float3 p) { return (double3)((double)p.z, (double)p.y, (double)p.x); }

__kernel void stl_facets(__global const float *pos, __global const int *faces, const int first, __global float *out,
                         __global int *zero_area)
{
    const int f = get_global_id(0);
    const int3 t = vload3(first + f, faces);
    const float3 pa = vload3(t.x, pos), pb = vload3(t.y, pos), pc = vload3(t.z, pos);
    const float3 a = pa.zyx, b = pb.zyx, c = pc.zyx;
    const float3 u = b - a, w = c - a;
    float3 n = (float3)(u.y * w.z - u.z * w.y, u.z * w.x - u.x * w.z, u.x * w.y - u.y * w.x);
    const float length = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    n = length > 0.0f ? n / length : (float3)(0.0f, 0.0f, 0.0f);
    __global float *row = out + 12 * (long)f;
    vstore3(n, 0, row);
    vstore3(a, 1, row);
    vstore3(b, 2, row);
    vstore3(c, 3, row);
    const double3 a64 = xyz64v(pa);
    const double3 u64 = xyz64v(pb) - a64, w64 = xyz64v(pc) - a64;
    const double n0 = u64.y * w64.z - u64.z * w64.y;
    const double n1 = u64.z * w64.x - u64.x * w64.z;
    const double n2 = u64.x * w64.y - u64.y * w64.x;
    if (n0 == 0.0 && n1 == 0.0 && n2 == 0.0) atomic_add(&zero_area[0], 1);
}

__kernel void gltf_vertices(__global const float *pos, __global const float *normals, __global const double *scales,
                            __global float *out_pos, __global float *out_normals)
{
    const int v = get_global_id(0);
    const double scale = scales[0];
    double p[3], n[3];
    xyz64(pos, v, p);
    out_pos[3 * (long)v] = (float)(p[0] * scale);
    out_pos[3 * (long)v + 1] = (float)(p[2] * scale);
    out_pos[3 * (long)v + 2] = (float)(-p[1] * scale);
    xyz64(normals, v, n);
    double g[3] = {n[0], n[2], -n[1]};
    const double length = sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
    if (length > 0.0 && isfinite(length)) {
        for (int k = 0; k < 3; k++) g[k] = g[k] / length;
    } else {
        g[0] = 0.0;
        g[1] = 1.0;
        g[2] = 0.0;
    }
    for (int k = 0; k < 3; k++) out_normals[3 * (long)v + k] = (float)g[k];
}
