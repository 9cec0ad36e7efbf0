"""Device mesh helpers shared by the mesh stages: vertex stars (incidence), vertex classes, compaction.

A device mesh is ``pos`` ``wp.array(dtype=wp.vec3)`` (z, y, x) mm and ``faces`` ``wp.array(dtype=wp.vec3i)``;
a removed face is ``(-1, -1, -1)``. Kernels are in ``engine.surface.kernels``
(``topology``, ``compaction``, ``measures``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from engine.report import Bounds, MeshStats

CLASS_NAMES = ("free", "border", "locked", "unused")  # the kernels' FREE, BORDER, LOCKED, DEAD


class Incidence:
    """Every vertex's star (the faces around it) as CSR: ``offset``, ``count``, ``star`` (sorted per vertex, so
    that every sum over a star runs in a fixed order)."""

    def __init__(self, n_vertices: int) -> None:
        import warp as wp

        self.count = wp.zeros(n_vertices, dtype=wp.int32)
        self.offset = wp.zeros(n_vertices, dtype=wp.int32)
        self.cursor = wp.zeros(n_vertices, dtype=wp.int32)
        self.star = wp.empty(0, dtype=wp.int32)

    def build(self, faces: Any, n_alive: int) -> Incidence:
        """(Re)build from ``faces``, of which ``n_alive`` are not removed."""
        import warp as wp

        from engine.surface.kernels import topology as ktopo

        self.count.zero_()
        self.cursor.zero_()
        wp.launch(ktopo.count_incidence, dim=len(faces), inputs=[faces, self.count])
        wp.utils.array_scan(self.count, self.offset, inclusive=False)
        if len(self.star) < 3 * n_alive:
            self.star = wp.empty(3 * n_alive, dtype=wp.int32)
        wp.launch(ktopo.fill_incidence, dim=len(faces), inputs=[faces, self.offset, self.cursor, self.star])
        wp.launch(ktopo.sort_incidence, dim=len(self.count), inputs=[self.offset, self.count, self.star])
        return self

    @property
    def inputs(self) -> list[Any]:
        return [self.offset, self.count, self.star]


def on_device(dev: Any, *arrays: Any) -> tuple[Any, ...]:
    """The arrays on ``dev``: themselves where they are there, else copies."""
    import warp as wp

    return tuple(a if a.device == dev else wp.clone(a, device=dev) for a in arrays)


def vertex_classes(faces: Any, inc: Incidence) -> Any:
    """Per vertex: FREE (one closed fan), BORDER (one open fan), LOCKED (non-manifold, inconsistent or degenerate
    surroundings) or DEAD (no face), as ``wp.array(dtype=wp.int32)``."""
    import warp as wp

    from engine.surface.kernels import topology as ktopo

    state = wp.empty(len(inc.count), dtype=wp.int32)
    wp.launch(ktopo.classify_vertices, dim=len(inc.count), inputs=[faces, *inc.inputs, state])
    return state


def exclusive_scan(flag: Any) -> tuple[Any, int]:
    """Exclusive prefix sum of an int32 0/1 array on its device, and the total (only the last entries are read
    back)."""
    import warp as wp

    n = len(flag)
    scan = wp.empty(n, dtype=wp.int32, device=flag.device)
    if n == 0:
        return scan, 0
    wp.utils.array_scan(flag, scan, inclusive=False)
    return scan, int(scan[n - 1 : n].numpy()[0] + flag[n - 1 : n].numpy()[0])  # sync point


def bounds(pos: Any) -> tuple[np.ndarray, np.ndarray]:
    """Component-wise minimum and maximum of device positions (a device reduction; 24 bytes come back)."""
    import warp as wp

    from engine.surface.kernels import compaction as kcompact

    box = wp.array(np.array([[np.inf] * 3, [-np.inf] * 3], np.float32), dtype=wp.vec3, device=pos.device)
    wp.launch(kcompact.bounds_kernel, dim=len(pos), inputs=[pos, box], device=pos.device)
    lo, hi = box.numpy()  # sync point
    return lo, hi


def compact_faces(faces: Any, n_alive: int) -> Any:
    """The faces that are not removed, in order (a new array of ``n_alive``)."""
    import warp as wp

    from engine.surface.kernels import compaction as kcompact

    flag = wp.empty(len(faces), dtype=wp.int32)
    wp.launch(kcompact.alive_flags, dim=len(faces), inputs=[faces, flag])
    slot, _ = exclusive_scan(flag)
    out = wp.empty(n_alive, dtype=wp.vec3i)
    wp.launch(kcompact.scatter_faces, dim=len(faces), inputs=[faces, slot, out])
    return out


def used_slots(pos: Any, faces: Any) -> tuple[Any, Any, int]:
    """Per vertex its face count and its slot among the used vertices; the number used."""
    import warp as wp

    from engine.surface.kernels import compaction as kcompact
    from engine.surface.kernels import topology as ktopo

    count = wp.zeros(len(pos), dtype=wp.int32)
    wp.launch(ktopo.count_incidence, dim=len(faces), inputs=[faces, count])
    flag = wp.empty(len(pos), dtype=wp.int32)
    wp.launch(kcompact.used_flags, dim=len(pos), inputs=[count, flag])
    slot, n_used = exclusive_scan(flag)
    return count, slot, n_used


def compact_vertices(pos: Any, faces: Any) -> tuple[Any, Any]:
    """Drop the vertices no face uses (the kept ones keep their order); ``faces`` is remapped in place."""
    import warp as wp

    from engine.surface.kernels import compaction as kcompact

    with wp.ScopedDevice(pos.device):
        count, slot, n_used = used_slots(pos, faces)
        if n_used == len(pos):
            return pos, faces
        out = wp.empty(n_used, dtype=wp.vec3)
        wp.launch(kcompact.scatter_vertices, dim=len(pos), inputs=[pos, count, slot, out])
        wp.launch(kcompact.remap_faces, dim=len(faces), inputs=[faces, slot])
    return out, faces


def bbox_centre(pos: Any) -> Any:
    """The centre of the vertices' bounding box as ``wp.vec3d`` (the quadrics' local origin)."""
    import warp as wp

    if len(pos) == 0:
        return wp.vec3d(0.0, 0.0, 0.0)
    lo, hi = bounds(pos)
    c = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
    return wp.vec3d(float(c[0]), float(c[1]), float(c[2]))


def component_labels_device(faces: Any, n_vertices: int) -> Any:
    """Connected components of a device mesh: per vertex the smallest vertex index of its piece (min-label hooking
    with pointer jumping; a handful of rounds for any mesh). An unused vertex is its own piece."""
    import warp as wp

    from engine.surface.kernels import measures as kmeasure

    label = wp.array(np.arange(n_vertices, dtype=np.int32), device=faces.device)
    changed = wp.zeros(1, dtype=wp.int32, device=faces.device)
    while True:
        changed.zero_()
        wp.launch(kmeasure.hook_labels, dim=len(faces), inputs=[faces, label, changed], device=faces.device)
        wp.launch(kmeasure.jump_labels, dim=n_vertices, inputs=[label], device=faces.device)
        if int(changed.numpy()[0]) == 0:  # sync point
            return label


def _face_sums(pos: Any, faces: Any) -> tuple[float, float, int]:
    """Signed volume (mm^3), area (mm^2) and degenerate faces of a device mesh: per-chunk sums on the device,
    added on the host in chunk order (the same mesh gives the same sums)."""
    import warp as wp

    from engine.budget import STATS_CHUNK_FACES
    from engine.surface.kernels import measures as kmeasure

    nf = len(faces)
    size = min(nf, STATS_CHUNK_FACES)  # no per-face array of the whole model
    if size == 0:
        return 0.0, 0.0, 0
    vol = wp.empty(size, dtype=wp.float64)
    area = wp.empty(size, dtype=wp.float64)
    degen = wp.empty(size, dtype=wp.float32)
    volume = area_sum = degenerate = 0.0
    for first in range(0, nf, size):
        n = min(size, nf - first)
        wp.launch(kmeasure.face_measures, dim=n, inputs=[pos, faces, first, vol, area, degen])
        volume += float(wp.utils.array_sum(vol[:n]))  # sync point
        area_sum += float(wp.utils.array_sum(area[:n]))
        degenerate += float(wp.utils.array_sum(degen[:n]))
    return volume, area_sum, round(degenerate)


def mesh_stats_device(pos: Any, faces: Any, inc: Incidence | None = None) -> MeshStats:
    """``engine.surface.meshcheck.mesh_stats`` of a device mesh, computed on its device (same keys and meaning: the
    report's ``mesh``, ``engine.report.MeshStats``): only counts and a few numbers come back to the host."""
    import warp as wp

    from engine.surface.kernels import measures as kmeasure

    nv, nf = len(pos), len(faces)
    with wp.ScopedDevice(pos.device):
        if inc is None:
            inc = Incidence(nv).build(faces, nf)
        totals = wp.zeros(4, dtype=wp.int64)
        wp.launch(kmeasure.edge_census, dim=nv, inputs=[faces, *inc.inputs, totals])
        volume, area_sum, degenerate = _face_sums(pos, faces)
        classes = np.bincount(vertex_classes(faces, inc).numpy(), minlength=4)
        label = component_labels_device(faces, nv)
        roots = wp.zeros(1, dtype=wp.int32)
        wp.launch(kmeasure.count_roots, dim=nv, inputs=[label, inc.count, roots])
        components = int(roots.numpy()[0]) + int(classes[3])  # unused vertices count as pieces, as on the host
        edges, border, nonmanifold, inconsistent = (int(x) for x in totals.numpy())
        bbox: Bounds | None = None
        if nv:
            lo, hi = bounds(pos)
            bbox = {"min": [float(x) for x in lo[::-1]], "max": [float(x) for x in hi[::-1]]}
    edge_ok = nonmanifold == 0 and inconsistent == 0 and degenerate == 0
    watertight = nf > 0 and border == 0 and nonmanifold == 0
    vman = bool(classes[2] == 0) if edge_ok and watertight else None
    return {
        "n_vertices": nv,
        "n_faces": nf,
        "n_edges": edges,
        "watertight": bool(watertight),
        "manifold": bool(edge_ok and vman is not False),
        "vertex_manifold": vman,
        "boundary_edges": border,
        "nonmanifold_edges": nonmanifold,
        "inconsistent_edges": inconsistent,
        "degenerate_faces": degenerate,
        "components": components,
        "euler": int(nv - edges + nf),
        "volume_mm3": volume,
        "area_mm2": area_sum,
        "bbox_mm": bbox,
    }
