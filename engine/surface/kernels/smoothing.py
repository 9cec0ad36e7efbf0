"""Warp kernels on triangle meshes: vertex normals and surface-preserving Laplacian smoothing.

Positions are ``wp.vec3`` in (z, y, x) mm; face normals are taken with vertices in (x, y, z) order, i.e. the
cross product of (z, y, x) edge vectors is negated (a reflection swaps handedness). OpenCL C twins, the same
arithmetic in the same order: ``smoothing.cl``.
"""

from __future__ import annotations

import warp as wp


@wp.func
def face_normal_zyx(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Area-weighted normal (twice the area) of triangle a, b, c, oriented for (x, y, z) order, in (z, y, x)."""
    return -wp.cross(b - a, c - a)


@wp.kernel
def star_neighbour_mean_kernel(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.vec3),
):
    """Mean of the other two vertices of every face around v (a fixed order: stars are sorted). Around a closed
    fan every neighbour appears twice, so this is the neighbours' mean; other vertices stay fixed anyway."""
    v = wp.tid()
    lo = offset[v]
    n = count[v]
    acc = wp.vec3(0.0)
    for i in range(n):
        t = faces[star[lo + i]]
        acc = acc + pos[t[0]] + pos[t[1]] + pos[t[2]] - pos[v]
    p = pos[v]
    if n > 0:
        p = acc / float(2 * n)
    cand[v] = p


@wp.kernel
def star_normals_kernel(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3),
):
    """Area-weighted unit vertex normal, summed over the vertex's star in a fixed order."""
    v = wp.tid()
    lo = offset[v]
    acc = wp.vec3(0.0)
    for i in range(count[v]):
        t = faces[star[lo + i]]
        acc = acc + face_normal_zyx(pos[t[0]], pos[t[1]], pos[t[2]])
    length = wp.length(acc)
    if length > 0.0:
        acc = acc / length
    out[v] = acc


@wp.kernel
def fixed_from_classes(state: wp.array(dtype=wp.int32), fixed: wp.array(dtype=wp.int32)):
    """Only vertices with one closed fan (class 0, FREE) may move."""
    i = wp.tid()
    fixed[i] = 0
    if state[i] != 0:
        fixed[i] = 1


@wp.func
def turns_too_far(n_old: wp.vec3, n_new: wp.vec3, cos_max: float) -> bool:
    lo = wp.length(n_old)
    ln = wp.length(n_new)
    bad = True
    if lo > 0.0 and ln > 0.0:
        bad = wp.dot(n_old, n_new) < cos_max * lo * ln
    return bad


@wp.kernel
def reject_kernel(
    pos: wp.array(dtype=wp.vec3),
    cand: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    cos_max: float,
    reject: wp.array(dtype=wp.int32),
):
    """A vertex may move only if none of its faces turns by more than the angle (its neighbours held still)."""
    f = wp.tid()
    t = faces[f]
    a = pos[t[0]]
    b = pos[t[1]]
    c = pos[t[2]]
    n_old = face_normal_zyx(a, b, c)
    if turns_too_far(n_old, face_normal_zyx(cand[t[0]], b, c), cos_max):
        reject[t[0]] = 1
    if turns_too_far(n_old, face_normal_zyx(a, cand[t[1]], c), cos_max):
        reject[t[1]] = 1
    if turns_too_far(n_old, face_normal_zyx(a, b, cand[t[2]]), cos_max):
        reject[t[2]] = 1


@wp.kernel
def accept_kernel(
    pos: wp.array(dtype=wp.vec3),
    cand: wp.array(dtype=wp.vec3),
    reject: wp.array(dtype=wp.int32),
    fixed: wp.array(dtype=wp.int32),
    moved: wp.array(dtype=wp.int32),
):
    """``cand`` becomes the new positions: a vertex's candidate where it may move, else its position."""
    i = wp.tid()
    if reject[i] == 0 and fixed[i] == 0:
        wp.atomic_add(moved, 0, 1)
    else:
        cand[i] = pos[i]


@wp.kernel
def violation_kernel(
    old: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    cos_max: float,
    revert: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """After simultaneous moves: a face that turned too far sends its moved vertices back."""
    f = wp.tid()
    t = faces[f]
    n_old = face_normal_zyx(old[t[0]], old[t[1]], old[t[2]])
    n_new = face_normal_zyx(pos[t[0]], pos[t[1]], pos[t[2]])
    if turns_too_far(n_old, n_new, cos_max):
        for k in range(3):
            if wp.length_sq(pos[t[k]] - old[t[k]]) > 0.0:
                revert[t[k]] = 1
                wp.atomic_add(count, 0, 1)


@wp.kernel
def revert_kernel(old: wp.array(dtype=wp.vec3), pos: wp.array(dtype=wp.vec3), revert: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if revert[i] != 0:
        pos[i] = old[i]
        revert[i] = 0
