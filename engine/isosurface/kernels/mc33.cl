/* OpenCL C kernels of Marching Cubes 33: block classification, per-cell counting and emission. The same
 * arithmetic, in the same order, as mc33.py's Warp kernels (read that file's docstring for the grid bookkeeping):
 * the same vertices and faces, bit for bit. No fused multiply-adds (Warp makes none), float literals only.
 * VOL_T is the volume's sample type (the program is built once per type by engine.backend.opencl_backend).
 * Arrays of vec3 / vec3i are packed float / int triples. */
#pragma OPENCL FP_CONTRACT OFF

#define BLOCK 8
#define BLOCK_CELLS (BLOCK * BLOCK * BLOCK)

typedef struct {
    int nz, ny, nx;
    int zoff; /* global z of plane 0 of the slab array */
    int bz0;  /* first block layer of the slab */
    int nbz, nby, nbx;
    int cz_first; /* first cell layer of the slab (owners below it are in plane_prev) */
    float level, pad;
    int closed;
    float tau, sz, sy, sx;
} Grid;

static bool inside(const Grid g, int z, int y, int x)
{
    return z >= 0 && z < g.nz && y >= 0 && y < g.ny && x >= 0 && x < g.nx;
}

static float raw(__global const VOL_T *vol, const Grid g, int z, int y, int x)
{
    return (float)vol[((long)(z - g.zoff) * g.ny + y) * g.nx + x];
}

/* value minus level; pad outside the array */
static float sample(__global const VOL_T *vol, const Grid g, int z, int y, int x)
{
    float s = g.pad;
    if (inside(g, z, y, x)) s = raw(vol, g, z, y, x) - g.level;
    return s;
}

static int corner_dz(int c) { return (c >> 2) & 1; }
static int corner_dy(int c) { return (c >> 1) & 1; }
static int corner_dx(int c) { return c & 1; }

static int edge_c0(int e)
{
    if (e < 4) return 2 * (e & 1) + 4 * (e >> 1);
    if (e < 8) return ((e - 4) & 1) + 4 * ((e - 4) >> 1);
    return ((e - 8) & 1) + 2 * ((e - 8) >> 1);
}

static int edge_step(int e) { return e < 4 ? 1 : (e < 8 ? 2 : 4); }

static void cell_values(__global const VOL_T *vol, const Grid g, int oz, int oy, int ox, float *v)
{
    for (int c = 0; c < 8; c++) v[c] = sample(vol, g, oz + corner_dz(c), oy + corner_dy(c), ox + corner_dx(c));
}

static int cell_config(const float *v)
{
    int cfg = 0;
    for (int c = 0; c < 8; c++)
        if (v[c] >= 0.0f) cfg |= 1 << c;
    return cfg;
}

static bool corner_inside(const Grid g, int oz, int oy, int ox, int c)
{
    return inside(g, oz + corner_dz(c), oy + corner_dy(c), ox + corner_dx(c));
}

static int edge_cut(const Grid g, const float *v, int oz, int oy, int ox, int e)
{
    const int c0 = edge_c0(e);
    const int c1 = c0 + edge_step(e);
    if ((v[c0] >= 0.0f) != (v[c1] >= 0.0f))
        if (g.closed != 0 || (corner_inside(g, oz, oy, ox, c0) && corner_inside(g, oz, oy, ox, c1))) return 1;
    return 0;
}

/* asymptotic decider on the ambiguous faces: bit f set when the positive diagonal is joined */
static int face_bits(const float *v, __global const int *face_cyc)
{
    int bits = 0;
    for (int f = 0; f < 6; f++) {
        const float a = v[face_cyc[4 * f + 0]];
        const float b = v[face_cyc[4 * f + 1]];
        const float c = v[face_cyc[4 * f + 2]];
        const float d = v[face_cyc[4 * f + 3]];
        const bool pa = a >= 0.0f;
        const bool pb = b >= 0.0f;
        if (pa == (c >= 0.0f) && pb == (d >= 0.0f) && pa != pb) {
            const float ac = a * c;
            const float bd = b * d;
            const bool joined = pa ? ac >= bd : bd >= ac;
            if (joined) bits |= 1 << f;
        }
    }
    return bits;
}

/* interior joins found by sweeping z (see mc33.py's body_bits) */
static int body_bits(const float *v)
{
    const float a0 = v[0], a1 = v[4], b0 = v[1], b1 = v[5], c0 = v[3], c1 = v[7], d0 = v[2], d1 = v[6];
    const float da = a1 - a0, db = b1 - b0, dc = c1 - c0, dd = d1 - d0;
    const float alpha = da * dc - db * dd;
    const float beta = a0 * dc + c0 * da - b0 * dd - d0 * db;
    int bits = 0;
    if (alpha != 0.0f) {
        const float t = -beta / (2.0f * alpha);
        if (t > 0.0f && t < 1.0f) {
            const float a = a0 + t * da, b = b0 + t * db, c = c0 + t * dc, d = d0 + t * dd;
            if (a >= 0.0f && c >= 0.0f && b < 0.0f && d < 0.0f) {
                const float q = a * c - b * d;
                if (alpha < 0.0f && q >= 0.0f) bits = 1;
                else if (alpha > 0.0f && q < 0.0f) bits = 8;
            } else if (a < 0.0f && c < 0.0f && b >= 0.0f && d >= 0.0f) {
                const float q2 = b * d - a * c;
                if (alpha > 0.0f && q2 >= 0.0f) bits = 2;
                else if (alpha < 0.0f && q2 < 0.0f) bits = 4;
            }
        }
    }
    return bits;
}

static int cell_triangulation(const Grid g, const float *v, int cfg, int oz, int oy, int ox,
                              __global const int *face_cyc, __global const int *key_map)
{
    int key = cfg | (face_bits(v, face_cyc) << 8);
    if (inside(g, oz, oy, ox) && inside(g, oz + 1, oy + 1, ox + 1)) key |= body_bits(v) << 14;
    return key_map[key];
}

static bool emits(const Grid g, int oz, int oy, int ox, int cfg)
{
    bool ok = cfg != 0 && cfg != 255;
    if (ok && g.closed == 0)
        ok = oz >= 0 && oy >= 0 && ox >= 0 && oz + 1 < g.nz && oy + 1 < g.ny && ox + 1 < g.nx;
    return ok;
}

static int3 slot_origin(const Grid g, __global const int *alist, int slot)
{
    const int b = alist[slot / BLOCK_CELLS];
    const int loc_cell = slot % BLOCK_CELLS;
    const int bx = b % g.nbx;
    const int by = (b / g.nbx) % g.nby;
    const int bz = b / (g.nbx * g.nby) + g.bz0;
    return (int3)(bz * BLOCK + loc_cell / (BLOCK * BLOCK) - 1, by * BLOCK + (loc_cell / BLOCK) % BLOCK - 1,
                  bx * BLOCK + loc_cell % BLOCK - 1);
}

__kernel void block(__global const VOL_T *vol, const Grid g, __global int *active, __global int *flags)
{
    const int b = (int)get_global_id(0);
    const int bx = b % g.nbx;
    const int by = (b / g.nbx) % g.nby;
    const int bz = b / (g.nbx * g.nby) + g.bz0;
    const int z0 = bz * BLOCK - 1, y0 = by * BLOCK - 1, x0 = bx * BLOCK - 1;
    int pos = 0, neg = 0, outside = 0;
    const int z1 = min(z0 + BLOCK, g.nz), y1 = min(y0 + BLOCK, g.ny), x1 = min(x0 + BLOCK, g.nx);
    if (z0 < 0 || y0 < 0 || x0 < 0 || z0 + BLOCK >= g.nz || y0 + BLOCK >= g.ny || x0 + BLOCK >= g.nx) outside = 1;
    for (int z = max(z0, 0); z < z1 + 1; z++) {
        if (pos == 1 && neg == 1) break;
        for (int y = max(y0, 0); y < y1 + 1; y++)
            for (int x = max(x0, 0); x < x1 + 1; x++)
                if (z < g.nz && y < g.ny && x < g.nx) {
                    if (raw(vol, g, z, y, x) - g.level >= 0.0f) pos = 1;
                    else neg = 1;
                }
    }
    if (pos == 1) flags[1] = 1;
    if (neg == 1) flags[0] = 1;
    if (outside == 1 && g.closed != 0) neg = 1;
    active[b] = pos * neg;
}

/* global size (nx, ny, nz) over a float slab */
__kernel void nan_check(__global const float *vol, __global int *flags)
{
    const long i = ((long)get_global_id(2) * get_global_size(1) + get_global_id(1)) * get_global_size(0)
                   + get_global_id(0);
    if (isnan(vol[i])) flags[2] = 1;
}

static int pack_code(int tid, int mask) { return (tid + 1) | (mask << 16); }
static int code_tri(int c) { return (c & 0xFFFF) - 1; }
static int code_mask(int c) { return c >> 16; }

static int owner_slot(const Grid g, __global const int *bmap, int oz, int oy, int ox)
{
    const int cz = oz + 1, cy = oy + 1, cx = ox + 1;
    const int b = ((cz / BLOCK - g.bz0) * g.nby + cy / BLOCK) * g.nbx + cx / BLOCK;
    const int loc_cell = ((cz % BLOCK) * BLOCK + (cy % BLOCK)) * BLOCK + (cx % BLOCK);
    return bmap[b] * BLOCK_CELLS + loc_cell;
}

/* owned-edge cuts: top-face x edge (2), top-face y edge (6), z edge (8) */
__kernel void count(__global const VOL_T *vol, const Grid g, __global const int *alist, __global const int *face_cyc,
                    __global const int *key_map, __global const int *tri_count, __global const int *ivert_count,
                    __global int *vcount, __global int *tcount, __global int *code, __global int *flags)
{
    const int slot = (int)get_global_id(0);
    const int3 o = slot_origin(g, alist, slot);
    int nv = 0, nt = 0, tid = -1, mask = 0;
    if (o.x < g.nz && o.y < g.ny && o.z < g.nx) {
        float v[8];
        cell_values(vol, g, o.x, o.y, o.z, v);
        const int cfg = cell_config(v);
        const int cx = edge_cut(g, v, o.x, o.y, o.z, 2);
        const int cy = edge_cut(g, v, o.x, o.y, o.z, 6);
        const int cz = edge_cut(g, v, o.x, o.y, o.z, 8);
        nv = cx + cy + cz;
        mask = cx | (cy << 1) | (cz << 2);
        if (emits(g, o.x, o.y, o.z, cfg)) {
            tid = cell_triangulation(g, v, cfg, o.x, o.y, o.z, face_cyc, key_map);
            if (tid < 0) {
                flags[3] = 1; /* key outside the generated tables: should never happen */
                tid = key_map[cfg];
            }
            nt = tri_count[tid];
            nv = nv + ivert_count[tid];
        }
    }
    vcount[slot] = nv;
    tcount[slot] = nt;
    code[slot] = pack_code(tid, mask);
}

/* global id of the vertex on edge ``kind`` (0 x, 1 y, 2 z) owned by the cell at origin (oz, oy, ox) */
static int owner_vertex(const Grid g, __global const int *bmap, __global const int *voff, __global const int *code,
                        __global const int *plane_prev, int vstart, int oz, int oy, int ox, int kind)
{
    if (oz < g.cz_first) return plane_prev[((long)kind * (g.ny + 1) + (oy + 1)) * (g.nx + 1) + (ox + 1)];
    const int slot = owner_slot(g, bmap, oz, oy, ox);
    const int mask = code_mask(code[slot]);
    int rank = 0;
    if (kind >= 1) rank += mask & 1;
    if (kind >= 2) rank += (mask >> 1) & 1;
    return vstart + voff[slot] + rank;
}

/* point where the level crosses edge e, as (z, y, x) in mm */
static float3 edge_point(const Grid g, const float *v, int oz, int oy, int ox, int e)
{
    const int c0 = edge_c0(e);
    const int c1 = c0 + edge_step(e);
    float t = 0.5f;
    if (corner_inside(g, oz, oy, ox, c0) && corner_inside(g, oz, oy, ox, c1)) {
        const float r = v[c0] / (v[c0] - v[c1]);
        const float hi = 1.0f - g.tau;
        t = r < g.tau ? g.tau : (r > hi ? hi : r);
    }
    float z = (float)(oz + corner_dz(c0));
    float y = (float)(oy + corner_dy(c0));
    float x = (float)(ox + corner_dx(c0));
    if (e < 4) x = x + t;
    else if (e < 8) y = y + t;
    else z = z + t;
    return (float3)(z * g.sz, y * g.sy, x * g.sx);
}

static int edge_owner_vertex(const Grid g, __global const int *bmap, __global const int *voff,
                             __global const int *code, __global const int *plane_prev, int vstart, int oz, int oy,
                             int ox, int e)
{
    const int kind = e / 4;
    const int lo = (e % 4) & 1;
    const int hi = (e % 4) >> 1;
    int wz = oz, wy = oy, wx = ox;
    if (kind == 0) {
        wz = oz + hi - 1;
        wy = oy + lo;
    } else if (kind == 1) {
        wz = oz + hi - 1;
        wx = ox + lo;
    } else {
        wx = ox + lo;
        wy = oy + hi;
    }
    return owner_vertex(g, bmap, voff, code, plane_prev, vstart, wz, wy, wx, kind);
}

static void put3f(__global float *a, int i, float3 p)
{
    a[3 * (long)i + 0] = p.x;
    a[3 * (long)i + 1] = p.y;
    a[3 * (long)i + 2] = p.z;
}

__kernel void emit(__global const VOL_T *vol, const Grid g, __global const int *alist, __global const int *bmap,
                   __global const int *voff, __global const int *toff, __global const int *code,
                   __global const int *plane_prev, const int vstart, __global const int *tri_offset,
                   __global const int *tri_count, __global const int *tri_local, __global const int *ivert_offset,
                   __global const int *ivert_count, __global const float *ivert_weights, __global float *verts,
                   __global int *faces)
{
    const int slot = (int)get_global_id(0);
    const int c = code[slot];
    const int tid = code_tri(c);
    const int mask = code_mask(c);
    if (mask == 0 && tid < 0) return;
    const int3 o = slot_origin(g, alist, slot);
    const int oz = o.x, oy = o.y, ox = o.z;
    float v[8];
    cell_values(vol, g, oz, oy, ox, v);
    const int base = voff[slot];
    int rank = 0;
    if ((mask & 1) != 0) put3f(verts, base + rank++, edge_point(g, v, oz, oy, ox, 2));
    if ((mask & 2) != 0) put3f(verts, base + rank++, edge_point(g, v, oz, oy, ox, 6));
    if ((mask & 4) != 0) put3f(verts, base + rank++, edge_point(g, v, oz, oy, ox, 8));
    if (tid < 0) return;
    int ids[12];
    float pz[12], py[12], px[12];
    for (int e = 0; e < 12; e++) {
        ids[e] = 0;
        pz[e] = py[e] = px[e] = 0.0f;
        if (edge_cut(g, v, oz, oy, ox, e) != 0) {
            const float3 pe = edge_point(g, v, oz, oy, ox, e);
            pz[e] = pe.x;
            py[e] = pe.y;
            px[e] = pe.z;
            ids[e] = edge_owner_vertex(g, bmap, voff, code, plane_prev, vstart, oz, oy, ox, e);
        }
    }
    const int ni = ivert_count[tid];
    const int i0 = ivert_offset[tid];
    for (int i = 0; i < ni; i++) {
        float qz = 0.0f, qy = 0.0f, qx = 0.0f;
        for (int e2 = 0; e2 < 12; e2++) {
            const float w = ivert_weights[(i0 + i) * 12 + e2];
            if (w != 0.0f) {
                const float wz = w * pz[e2], wy = w * py[e2], wx = w * px[e2];
                qz = qz + wz;
                qy = qy + wy;
                qx = qx + wx;
            }
        }
        put3f(verts, base + rank + i, (float3)(qz, qy, qx));
    }
    const int gbase = vstart + base + rank;
    const int t0 = tri_offset[tid];
    const int nt = tri_count[tid];
    const int out = toff[slot];
    for (int t = 0; t < nt; t++)
        for (int k = 0; k < 3; k++) {
            const int loc = tri_local[3 * (t0 + t) + k];
            faces[3 * (long)(out + t) + k] = loc < 12 ? ids[loc] : gbase + loc - 12;
        }
}

/* ids of the x and y edge vertices of sample plane oz + 1 (owned by cell layer oz), for the next slab;
 * global size (nx + 1, ny + 1) */
__kernel void plane(const Grid g, __global const int *bmap, __global const int *voff, __global const int *code,
                    const int vstart, const int oz, __global int *plane_next)
{
    const int i = (int)get_global_id(0);
    const int j = (int)get_global_id(1);
    int idx = -1, idy = -1;
    const int b = (((oz + 1) / BLOCK - g.bz0) * g.nby + j / BLOCK) * g.nbx + i / BLOCK;
    if (bmap[b] >= 0) {
        const int slot = owner_slot(g, bmap, oz, j - 1, i - 1);
        const int mask = code_mask(code[slot]);
        const int first = vstart + voff[slot];
        if ((mask & 1) != 0) {
            idx = first;
            idy = first + 1;
        } else {
            idy = first;
        }
        if ((mask & 2) == 0) idy = -1;
    }
    const long plane_size = (long)(g.ny + 1) * (g.nx + 1);
    plane_next[(long)j * (g.nx + 1) + i] = idx;
    plane_next[plane_size + (long)j * (g.nx + 1) + i] = idy;
}
