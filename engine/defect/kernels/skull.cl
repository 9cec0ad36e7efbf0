/* OpenCL C twins of skull.py's Warp kernels: the bone's 26-connected pieces by min-label hooking with pointer
 * jumping (every voxel ends labelled with the flat index of its piece's first voxel), their sizes, and the mask of
 * one piece. Volumes are flat (z, y, x) arrays, labels int (-1: not bone). One-dimensional launches: id 0 is the
 * voxel (or the piece). */

/* label = the voxel's own flat index where it is bone, else -1 */
__kernel void init(__global const uchar *bone, __global int *label)
{
    const int i = (int)get_global_id(0);
    label[i] = bone[i] != 0 ? i : -1;
}

/* hook voxels i and j (both bone, neighbours) onto the smaller of their labels; 1 where a label changed */
static int pull(__global int *label, const int i, const int j)
{
    const int a = label[i];
    const int b = label[j];
    if (a == b) return 0;
    const int m = min(a, b);
    if (a > m) {
        atomic_min(&label[a], m);
        atomic_min(&label[i], m);
    }
    if (b > m) {
        atomic_min(&label[b], m);
        atomic_min(&label[j], m);
    }
    return 1;
}

/* every bone voxel pulls itself and its 13 forward 26-neighbours that are bone (later in the flat order: each pair
 * once) down to the smaller label, and their labels' voxels too */
__kernel void hook(const int nz, const int ny, const int nx, __global int *label, __global int *changed)
{
    const int i = (int)get_global_id(0);
    if (label[i] < 0) return;
    const int z = i / (ny * nx);
    const int rest = i - z * (ny * nx);
    const int y = rest / nx;
    const int x = rest - y * nx;
    int moved = 0;
    for (int c = 0; c < 13; c++) {
        /* the 13 offsets after (0, 0, 0) in (z, y, x) order: (0, 0, 1), (0, 1, -1..1), (1, -1..1, -1..1) */
        const int k = c + 14;
        const int zz = z + k / 9 - 1;
        const int yy = y + (k / 3) % 3 - 1;
        const int xx = x + k % 3 - 1;
        if (zz < nz && yy >= 0 && yy < ny && xx >= 0 && xx < nx) {
            const int j = (zz * ny + yy) * nx + xx;
            if (label[j] >= 0) moved += pull(label, i, j);
        }
    }
    if (moved != 0) changed[0] = 1;
}

/* size[root] += 1 for every bone voxel; flags = 1 at the roots (each piece's first voxel) */
__kernel void roots(__global const int *label, __global int *size, __global int *flags)
{
    const int i = (int)get_global_id(0);
    const int r = label[i];
    int f = 0;
    if (r >= 0) {
        atomic_add(&size[r], 1);
        if (r == i) f = 1;
    }
    flags[i] = f;
}

/* out[k] = src[at[k]] */
__kernel void gather(__global const int *src, __global const int *at, __global int *out)
{
    const int k = (int)get_global_id(0);
    out[k] = src[at[k]];
}

/* out = 1 in the piece whose root is root, else 0 */
__kernel void piece(__global const int *label, const int root, __global uchar *out)
{
    const int i = (int)get_global_id(0);
    out[i] = label[i] == root ? 1 : 0;
}
