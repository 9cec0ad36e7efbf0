"""Device mesh helpers shared by the mesh stages: vertex stars (incidence), vertex classes, compaction, measures.

A device mesh is ``pos`` (V) packed (z, y, x) mm float triples and ``faces`` (F) packed int triples on one backend
(``engine.backend``: ``wp.array(dtype=wp.vec3)`` / ``wp.array(dtype=wp.vec3i)`` on Warp, ``VEC3F`` / ``VEC3I``
arrays on OpenCL); a removed face is ``(-1, -1, -1)``. The host code here is written once over the backend it finds
the arrays on; the kernels (``engine.surface.kernel_specs``) are in ``engine.surface.kernels``, Warp (``*.py``)
and OpenCL C (``*.cl``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I
from engine.surface import kernel_specs as k
from engine.surface.ops import backend_of, sum_f64

if TYPE_CHECKING:
    from engine.report import Bounds, MeshStats

CLASS_NAMES = ("free", "border", "locked", "unused")  # the kernels' FREE, BORDER, LOCKED, DEAD


class Incidence:
    """Every vertex's star (the faces around it) as CSR: ``offset``, ``count``, ``star`` (sorted per vertex, so
    that every sum over a star runs in a fixed order), on the backend of the faces it is built from."""

    def __init__(self, n_vertices: int) -> None:
        self.n = n_vertices
        self.backend: Any = None
        self.count: Any = None
        self.offset: Any = None
        self.cursor: Any = None
        self.star: Any = None

    def _allocate(self, bk: Any) -> None:
        self.backend = bk
        self.count = bk.zeros(self.n, np.int32)
        self.offset = bk.zeros(self.n, np.int32)
        self.cursor = bk.zeros(self.n, np.int32)
        self.star = bk.empty(0, np.int32)

    def build(self, faces: Any, n_alive: int) -> Incidence:
        """(Re)build from ``faces``, of which ``n_alive`` are not removed."""
        bk = backend_of(faces)
        if self.backend is not bk:
            self._allocate(bk)
        bk.fill(self.count, 0)
        bk.fill(self.cursor, 0)
        bk.launch(k.COUNT_INCIDENCE, len(faces), [faces, self.count])
        bk.exclusive_scan(self.count, self.offset)
        if len(self.star) < 3 * n_alive:
            self.star = bk.empty(3 * n_alive, np.int32)
        bk.launch(k.FILL_INCIDENCE, len(faces), [faces, self.offset, self.cursor, self.star])
        bk.launch(k.SORT_INCIDENCE, self.n, [self.offset, self.count, self.star])
        return self

    @property
    def inputs(self) -> list[Any]:
        return [self.offset, self.count, self.star]


def on_device(dev: Any, *arrays: Any) -> tuple[Any, ...]:
    """The arrays on ``dev`` (a Warp device or spec, or an ``engine.backend.Backend``): themselves where they are
    there, else copies (Warp to Warp directly, between backends through the host)."""
    from engine.surface.ops import dtype_of, get_backend

    target = get_backend(dev)

    def moved(a: Any) -> Any:
        here = backend_of(a)
        if here is target:
            return a
        if here.kind == target.kind == "warp":
            import warp as wp

            return wp.clone(a, device=target.device)  # type: ignore[attr-defined]
        return target.from_host(here.to_host(a), dtype_of(a))

    return tuple(moved(a) for a in arrays)


def vertex_classes(faces: Any, inc: Incidence) -> Any:
    """Per vertex: FREE (one closed fan), BORDER (one open fan), LOCKED (non-manifold, inconsistent or degenerate
    surroundings) or DEAD (no face), as a device int32 array."""
    bk = backend_of(faces)
    state = bk.empty(inc.n, np.int32)
    bk.launch(k.CLASSIFY, inc.n, [faces, *inc.inputs, state])
    return state


def class_counts(state: Any) -> np.ndarray:
    """How many vertices of each class (``CLASS_NAMES``' order), counted on the device (a sync point: 16 bytes
    come back; reading the class of each of the phantom's 15 M vertices back cost 0.14 s on an H200). The kernel
    counts all but the free vertices, which are the rest."""
    bk = backend_of(state)
    counts = bk.zeros(len(CLASS_NAMES), np.int32)
    if len(state):
        bk.launch(k.COUNT_CLASSES, len(state), [state, counts])
    out = bk.to_host(counts).astype(np.int64)
    out[0] = len(state) - out[1:].sum()
    return out


def exclusive_scan(flag: Any) -> tuple[Any, int]:
    """Exclusive prefix sum of an int32 0/1 array on its device, and the total (a sync point)."""
    bk = backend_of(flag)
    scan = bk.empty(len(flag), np.int32)
    return scan, bk.exclusive_scan(flag, scan)


def bounds(pos: Any) -> tuple[np.ndarray, np.ndarray]:
    """Component-wise minimum and maximum of device positions (a device reduction; 24 bytes come back)."""
    bk = backend_of(pos)
    box = bk.from_host(np.array([[np.inf] * 3, [-np.inf] * 3], np.float32), VEC3F)
    bk.launch(k.BOUNDS, len(pos), [pos, box])
    lo, hi = bk.to_host(box)  # sync point
    return lo, hi


def compact_faces(faces: Any, n_alive: int) -> Any:
    """The faces that are not removed, in order (a new array of ``n_alive``)."""
    bk = backend_of(faces)
    flag = bk.empty(len(faces), np.int32)
    bk.launch(k.ALIVE_FLAGS, len(faces), [faces, flag])
    slot, _ = exclusive_scan(flag)
    out = bk.empty(n_alive, VEC3I)
    bk.launch(k.SCATTER_FACES, len(faces), [faces, slot, out])
    return out


def used_slots(pos: Any, faces: Any) -> tuple[Any, Any, int]:
    """Per vertex its face count and its slot among the used vertices; the number used."""
    bk = backend_of(pos)
    count = bk.zeros(len(pos), np.int32)
    bk.launch(k.COUNT_INCIDENCE, len(faces), [faces, count])
    flag = bk.empty(len(pos), np.int32)
    bk.launch(k.USED_FLAGS, len(pos), [count, flag])
    slot, n_used = exclusive_scan(flag)
    return count, slot, n_used


def compact_vertices(pos: Any, faces: Any) -> tuple[Any, Any]:
    """Drop the vertices no face uses (the kept ones keep their order); ``faces`` is remapped in place."""
    bk = backend_of(pos)
    count, slot, n_used = used_slots(pos, faces)
    if n_used == len(pos):
        return pos, faces
    out = bk.empty(n_used, VEC3F)
    bk.launch(k.SCATTER_VERTICES, len(pos), [pos, count, slot, out])
    bk.launch(k.REMAP_FACES, len(faces), [faces, slot])
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
    bk = backend_of(faces)
    label = bk.empty(n_vertices, np.int32)
    if n_vertices:
        bk.launch(k.OWN_LABELS, n_vertices, [label])
    changed = bk.zeros(1, np.int32)
    while True:
        bk.fill(changed, 0)
        bk.launch(k.HOOK_LABELS, len(faces), [faces, label, changed])
        bk.launch(k.JUMP_LABELS, n_vertices, [label])
        if int(bk.to_host(changed)[0]) == 0:  # sync point
            return label


def _face_sums(pos: Any, faces: Any) -> tuple[float, float, int]:
    """Signed volume (mm^3), area (mm^2) and degenerate faces of a device mesh: per-face values in chunks, summed
    on the device in runs and the runs on the host, in order (the same mesh gives the same sums on every
    backend)."""
    from engine.budget import STATS_CHUNK_FACES

    bk = backend_of(pos)
    nf = len(faces)
    size = min(nf, STATS_CHUNK_FACES)  # no per-face array of the whole model
    if size == 0:
        return 0.0, 0.0, 0
    vol = bk.empty(size, np.float64)
    area = bk.empty(size, np.float64)
    degen = bk.empty(size, np.float64)
    runs = bk.empty(min(size, 1024), np.float64)
    volume = area_sum = degenerate = 0.0
    for first in range(0, nf, size):
        n = min(size, nf - first)
        bk.launch(k.FACE_MEASURES, n, [pos, faces, first, vol, area, degen])
        volume += sum_f64(bk, vol, n, runs)  # sync point
        area_sum += sum_f64(bk, area, n, runs)
        degenerate += sum_f64(bk, degen, n, runs)
    return volume, area_sum, round(degenerate)


def mesh_stats_device(pos: Any, faces: Any, inc: Incidence | None = None) -> MeshStats:
    """``engine.surface.meshcheck.mesh_stats`` of a device mesh, computed on its device (same keys and meaning: the
    report's ``mesh``, ``engine.report.MeshStats``): only counts and a few numbers come back to the host."""
    bk = backend_of(pos)
    nv, nf = len(pos), len(faces)
    if inc is None:
        inc = Incidence(nv).build(faces, nf)
    totals = bk.zeros(4, np.int64)
    bk.launch(k.EDGE_CENSUS, nv, [faces, *inc.inputs, totals])
    volume, area_sum, degenerate = _face_sums(pos, faces)
    classes = class_counts(vertex_classes(faces, inc))
    label = component_labels_device(faces, nv)
    roots = bk.zeros(1, np.int32)
    bk.launch(k.COUNT_ROOTS, nv, [label, inc.count, roots])
    components = int(bk.to_host(roots)[0]) + int(classes[3])  # unused vertices count as pieces, as on the host
    edges, border, nonmanifold, inconsistent = (int(x) for x in bk.to_host(totals))
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
