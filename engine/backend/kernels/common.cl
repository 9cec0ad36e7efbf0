/* Helpers shared by the mesh kernels' OpenCL C (included with `#include "common.cl"`, inlined once by
 * engine.backend.opencl_backend): the vertex classes and a face's corners around one of its vertices, as the Warp
 * kernels compute them. Faces are packed int triples; a removed face is (-1, -1, -1). */

#define FREE 0
#define BORDER 1
#define LOCKED 2
#define DEAD 3

static int3 face(__global const int *faces, const int f) { return vload3(f, faces); }
static int has_vertex(const int3 t, const int v) { return t.x == v || t.y == v || t.z == v; }

/* the corner after v in t (counter-clockwise) */
static int next_of(const int3 t, const int v)
{
    int r = t.x;
    if (t.x == v) r = t.y;
    else if (t.y == v) r = t.z;
    return r;
}

/* the corner before v in t */
static int prev_of(const int3 t, const int v)
{
    int r = t.y;
    if (t.x == v) r = t.z;
    else if (t.y == v) r = t.x;
    return r;
}
