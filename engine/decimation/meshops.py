"""The device mesh under decimation, on any backend (``engine.backend.Backend``): every vertex's star
(``Stars``, sorted CSR), the vertex classes, compaction, the bounding box, quadric arrays and the kernel arguments
the two backends spell differently (a float64, an int64, a vec3, the quadrics' origin).

The same work as ``engine.surface.devmesh`` (the same kernels on both backends; ``used_slots`` and
``compact_vertices`` are devmesh's own), written over the backend interface for the decimation's host loop, which
avoids devmesh's sync points where it can (``Stars`` and ``compact_faces`` scan without reading the total back). A
few helpers branch on ``backend.kind`` where the interface has no word yet (each a candidate ``Backend`` method):
``quadrics`` / ``quadrics_from_host`` / ``copy_quadrics`` (arrays of 10-double quadrics), ``clone``, ``scan`` (a
scan whose total is not read back: no sync point), ``sort_pairs`` (a stable key-value sort; on the host for
OpenCL), ``recorded`` (a launch packed once and replayed, Warp's ``record_cmd``) and ``f64`` / ``i64`` (the
OpenCL backend passes a Python or numpy float as float32, so a float64 goes as a 0-d array).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, Backend, Kernel
from engine.decimation import kernel_specs as K
from engine.surface import devmesh

ORIGIN_DTYPE = np.dtype([("x", np.float64), ("y", np.float64), ("z", np.float64)])  # OpenCL's ``origin_t``


# -- what the interface has no word for yet -----------------------------------------------------------------------
def quadrics(be: Backend, n: int) -> Any:
    """An uninitialised array of ``n`` quadrics (10 float64 each: Warp's ``kernels.quadrics.quadric``)."""
    if be.kind == "warp":
        import warp as wp

        from engine.decimation.kernels.quadrics import quadric

        return wp.empty(n, dtype=quadric, device=be.device)  # type: ignore[attr-defined]
    return be.empty((n, 10), np.float64)


def quadrics_from_host(be: Backend, host: np.ndarray) -> Any:
    """Quadrics (an (n, 10) float64 array) on the device."""
    host = np.ascontiguousarray(host, np.float64).reshape(-1, 10)
    if be.kind == "warp":
        import warp as wp

        from engine.decimation.kernels.quadrics import quadric

        return wp.array(host, dtype=quadric, device=be.device)  # type: ignore[attr-defined]
    out = be.empty((len(host), 10), np.float64)
    be.upload(out, host)
    return out


def copy_quadrics(be: Backend, dst: Any, src: Any, dst_row: int) -> None:
    """All of ``src``'s quadrics into ``dst`` from quadric ``dst_row``."""
    if be.kind == "warp":
        be.copy(dst, src, dst_offset=dst_row, count=len(src))
        return
    be.copy(dst, src, dst_offset=10 * dst_row, count=10 * len(src))  # (n, 10) float64: counted in doubles


def clone(be: Backend, arr: Any) -> Any:
    """A new device array with ``arr``'s values."""
    if be.kind == "warp":
        import warp as wp

        return wp.clone(arr)
    out = be.empty(arr.shape, arr.dtype)
    be.copy(out, arr)
    return out


def scan(be: Backend, src: Any, dst: Any) -> None:
    """Exclusive prefix sum of an int32 array, its total not read back (no sync point on Warp)."""
    if be.kind == "warp":
        import warp as wp

        if len(src):
            wp.utils.array_scan(src, dst, inclusive=False)
        return
    be.exclusive_scan(src, dst)


def recorded(be: Backend, kernel: Kernel, dim: int, args: list[Any]) -> Callable[[], None]:
    """A launch packed once and run by calling it (Warp records the command: packing the arguments of a short
    kernel costs more than its launch)."""
    if be.kind == "warp":
        import warp as wp

        from engine.backend.warp_backend import _resolve

        cmd = wp.launch(_resolve(kernel.warp), dim=dim, inputs=args, device=be.device, record_cmd=True)  # type: ignore[attr-defined]
        return cmd.launch  # type: ignore[no-any-return]
    return lambda: be.launch(kernel, dim, args)


def sort_pairs(be: Backend, keys: Any, values: Any, n: int) -> None:
    """Sort the first ``n`` int64 ``keys`` and their int32 ``values`` by key, stably (equal keys keep their order),
    in place; both arrays hold at least ``2 n`` elements (Warp's radix sort works in their second halves). Without
    a device sort on the interface, the OpenCL backend sorts on the host (a sync point; the same stable order)."""
    if n == 0:
        return
    if be.kind == "warp":
        import warp as wp

        wp.utils.radix_sort_pairs(keys, values, n)
        return
    k, v = be.to_host(keys, n), be.to_host(values, n)
    order = np.argsort(k, kind="stable")
    be.upload(keys, k[order])
    be.upload(values, v[order])


# -- kernel arguments ---------------------------------------------------------------------------------------------
def f64(be: Backend, x: float) -> Any:
    """A float64 kernel argument."""
    if be.kind == "warp":
        import warp as wp

        return wp.float64(x)
    return np.array(x, np.float64)  # a 0-d array: the backend takes a Python float (and np.float64) as float32


def i64(be: Backend, x: int) -> Any:
    """An int64 kernel argument."""
    if be.kind == "warp":
        import warp as wp

        return wp.int64(x)
    return np.array(x, np.int64)


def xyz(origin: Any) -> tuple[float, float, float]:
    """The three coordinates of an origin in any of its forms (``wp.vec3d``, an ``ORIGIN_DTYPE`` record, a
    sequence)."""
    if isinstance(origin, np.ndarray) and origin.dtype == ORIGIN_DTYPE:
        return float(origin["x"]), float(origin["y"]), float(origin["z"])
    return float(origin[0]), float(origin[1]), float(origin[2])


def vec3f_arg(be: Backend, v: Sequence[float]) -> Any:
    """Three float32 as a kernel argument (``wp.vec3`` / a struct of 3 floats)."""
    if be.kind == "warp":
        import warp as wp

        return wp.vec3(*(float(x) for x in v))
    rec = np.zeros((), [("x", np.float32), ("y", np.float32), ("z", np.float32)])
    rec["x"], rec["y"], rec["z"] = (float(x) for x in v)
    return rec


def origin_arg(be: Backend, origin: Sequence[float] | Any) -> Any:
    """The quadrics' local origin as a kernel argument (``wp.vec3d`` / an ``origin_t`` struct)."""
    x, y, z = xyz(origin)
    if be.kind == "warp":
        import warp as wp

        return wp.vec3d(x, y, z)
    rec = np.zeros((), ORIGIN_DTYPE)
    rec["x"], rec["y"], rec["z"] = x, y, z
    return rec


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
        scan(be, self.count, self.offset)
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
    scan(be, flag, slot)
    out = be.empty(n_alive, VEC3I)
    be.launch(K.SCATTER_FACES, len(faces), [faces, slot, out])
    return out


def compact_carrying(be: Backend, pos: Any, faces: Any, quad: Any) -> tuple[Any, Any, Any, Any]:
    """``engine.surface.devmesh.compact_vertices`` that also carries the quadrics and says where each kept vertex
    was: ``(pos, faces, quad, kept)`` with ``kept[i]`` the input index of output vertex ``i``."""
    count, slot, n_used = devmesh.used_slots(pos, faces)
    out = be.empty(n_used, VEC3F)
    kept = be.empty(n_used, np.int32)
    out_quad = quadrics(be, n_used)
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
