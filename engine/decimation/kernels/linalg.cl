/* float64 vectors and 3x3 solves as Warp's native code computes them (warp/native/vec.h, mat.h), never OpenCL's
 * builtins (which may fuse or reorder); shared by price.cl and cluster.cl (`#include "linalg.cl"`, inlined once by
 * engine.backend.opencl_backend). The including file sets `#pragma OPENCL FP_CONTRACT OFF` and cl_khr_fp64. */

typedef struct {
    double x, y, z;
} origin_t;

static double3 d3(const double x, const double y, const double z) { return (double3)(x, y, z); }
static double dot3(const double3 a, const double3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
static double3 cross3(const double3 a, const double3 b)
{
    return d3(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}
static double dmax(const double a, const double b) { return a > b ? a : b; }
static double dmin(const double a, const double b) { return a < b ? a : b; }

static double det3(const double m[9])
{
    const double3 r0 = d3(m[0], m[1], m[2]), r1 = d3(m[3], m[4], m[5]), r2 = d3(m[6], m[7], m[8]);
    return dot3(r0, cross3(r1, r2));
}

/* -(inverse(m) @ v), as Warp: the adjugate times 1 / det, then columns times the vector's components. */
static double3 solve3(const double m[9], const double det, const double3 v)
{
    double b[9];
    b[0] = m[4] * m[8] - m[5] * m[7];
    b[3] = m[5] * m[6] - m[3] * m[8];
    b[6] = m[3] * m[7] - m[4] * m[6];
    b[1] = m[2] * m[7] - m[1] * m[8];
    b[4] = m[0] * m[8] - m[2] * m[6];
    b[7] = m[1] * m[6] - m[0] * m[7];
    b[2] = m[1] * m[5] - m[2] * m[4];
    b[5] = m[2] * m[3] - m[0] * m[5];
    b[8] = m[0] * m[4] - m[1] * m[3];
    const double rcp = 1.0 / det;
    for (int k = 0; k < 9; k++) b[k] = b[k] * rcp;
    double3 r = d3(b[0] * v.x, b[3] * v.x, b[6] * v.x);
    r = r + d3(b[1] * v.y, b[4] * v.y, b[7] * v.y);
    r = r + d3(b[2] * v.z, b[5] * v.z, b[8] * v.z);
    return -r;
}
