"""The device mesh under decimation, on any backend (``engine.backend.Backend``): every vertex's star
(``Stars``, sorted CSR), the vertex classes, compaction, the bounding box and the quadrics' origin argument.

The same work as ``engine.surface.devmesh`` (the same kernels on both backends; ``used_slots`` and
``compact_vertices`` are devmesh's own), written over the backend interface for the decimation's host loop, which
avoids devmesh's sync points where it can (``Stars`` and ``compact_faces`` scan with ``Backend.prefix_sum``, which
does not read the total back). Nothing here branches on the backend: quadric arrays are ``VEC10D`` arrays, and
float64 / int64 / vector arguments, recorded launches and the key-value sort are ``Backend`` methods.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, VEC10D, Backend
from engine.decimation import kernel_specs as K
from engine.surface import devmesh


def xyz(origin: Any) -> tuple[float, float, float]:
    """The three coordinates of an origin in any of its forms (``wp.vec3d``, an ``origin_t`` record, a sequence)."""
    if isinstance(origin, np.ndarray) and origin.dtype.names == ("x", "y", "z"):
        return float(origin["x"]), float(origin["y"]), float(origin["z"])
    return float(origin[0]), float(origin[1]), float(origin[2])


def origin_arg(be: Backend, origin: Sequence[float] | Any) -> Any:
    """The quadrics' local origin as a kernel argument (``wp.vec3d`` / an ``origin_t`` struct)."""
    return be.vector(xyz(origin), np.float64)


# -- the mesh -----------------------------------------------------------------------------------------------------
class Stars:
    """Every vertex's star (the faces around it) as CSR: ``offset``, ``count``, ``star`` (sorted per vertex, so
    that every sum over a star runs in a fixed order): ``engine.surface.devmesh.Incidence`` on any backend."""

    def __init__(self, be: Backend, n_vertices: int) -> None:
        self.be = be
        self.count = be.zeros(n_vertices, np.int32)
        self.offset = be.zeros(n_vertices, np.int32)
        self.cursor = be.zeros(n_vertices, np.int32)
        self.star = be.empty(1, np.int32)
        self.capacity = 0

    def build(self, faces: Any, n_alive: int) -> Stars:
        """(Re)build from ``faces``, of which ``n_alive`` are not removed."""
        be, nv = self.be, len(self.count)
        be.fill(self.count, 0)
        be.fill(self.cursor, 0)
        be.launch(K.COUNT_INCIDENCE, len(faces), [faces, self.count])
        be.prefix_sum(self.count, self.offset)
        if self.capacity < 3 * n_alive:
            self.capacity = 3 * n_alive
            self.star = be.empty(max(self.capacity, 1), np.int32)
        be.launch(K.FILL_INCIDENCE, len(faces), [faces, self.offset, self.cursor, self.star])
        be.launch(K.SORT_INCIDENCE, nv, [self.offset, self.count, self.star])
        return self

    @property
    def inputs(self) -> list[Any]:
        return [self.offset, self.count, self.star]


def vertex_classes(be: Backend, faces: Any, stars: Stars) -> Any:
    """Per vertex: FREE, BORDER, LOCKED or DEAD (``engine.surface.devmesh.vertex_classes``)."""
    state = be.empty(len(stars.count), np.int32)
    be.launch(K.CLASSIFY, len(stars.count), [faces, *stars.inputs, state])
    return state


def compact_faces(be: Backend, faces: Any, n_alive: int) -> Any:
    """The faces that are not removed, in order (a new array of ``n_alive``)."""
    flag = be.empty(len(faces), np.int32)
    be.launch(K.ALIVE_FLAGS, len(faces), [faces, flag])
    slot = be.empty(len(faces), np.int32)
    be.prefix_sum(flag, slot)
    out = be.empty(n_alive, VEC3I)
    be.launch(K.SCATTER_FACES, len(faces), [faces, slot, out])
    return out


def compact_carrying(be: Backend, pos: Any, faces: Any, quad: Any) -> tuple[Any, Any, Any, Any]:
    """``engine.surface.devmesh.compact_vertices`` that also carries the quadrics and says where each kept vertex
    was: ``(pos, faces, quad, kept)`` with ``kept[i]`` the input index of output vertex ``i``."""
    count, slot, n_used = devmesh.used_slots(pos, faces)
    out = be.empty(n_used, VEC3F)
    kept = be.empty(n_used, np.int32)
    out_quad = be.empty(n_used, VEC10D)
    be.launch(K.SCATTER_VERTICES, len(pos), [pos, count, slot, out])
    be.launch(K.SCATTER_KEPT, len(pos), [count, slot, quad, kept, out_quad])
    be.launch(K.REMAP_FACES, len(faces), [faces, slot])
    return out, faces, out_quad, kept


def bounds(be: Backend, pos: Any) -> tuple[np.ndarray, np.ndarray]:
    """Component-wise minimum and maximum of device positions (a sync point: 24 bytes come back)."""
    box = be.from_host(np.array([[np.inf] * 3, [-np.inf] * 3], np.float32), VEC3F)
    if len(pos):
        be.launch(K.BOUNDS, len(pos), [pos, box])
    lo, hi = be.to_host(box)
    return lo, hi


def bbox_centre(be: Backend, pos: Any) -> np.ndarray:
    """The centre of the vertices' bounding box, float64 (a sync point)."""
    if len(pos) == 0:
        return np.zeros(3)
    lo, hi = bounds(be, pos)
    return np.asarray(0.5 * (lo.astype(np.float64) + hi.astype(np.float64)))
