"""Device mesh helpers shared by the mesh stages: vertex stars (incidence), vertex classes, compaction.

A device mesh is ``pos`` ``wp.array(dtype=wp.vec3)`` (z, y, x) mm and ``faces`` ``wp.array(dtype=wp.vec3i)``;
a removed face is ``(-1, -1, -1)``. Kernels are in ``engine.kernels.decimate``.
"""

from __future__ import annotations

from typing import Any

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

        from engine.kernels import decimate as kd

        self.count.zero_()
        self.cursor.zero_()
        wp.launch(kd.count_incidence, dim=len(faces), inputs=[faces, self.count])
        wp.utils.array_scan(self.count, self.offset, inclusive=False)
        if len(self.star) < 3 * n_alive:
            self.star = wp.empty(3 * n_alive, dtype=wp.int32)
        wp.launch(kd.fill_incidence, dim=len(faces), inputs=[faces, self.offset, self.cursor, self.star])
        wp.launch(kd.sort_incidence, dim=len(self.count), inputs=[self.offset, self.count, self.star])
        return self

    @property
    def inputs(self) -> list[Any]:
        return [self.offset, self.count, self.star]


def vertex_classes(faces: Any, inc: Incidence) -> Any:
    """Per vertex: FREE (one closed fan), BORDER (one open fan), LOCKED (non-manifold, inconsistent or degenerate
    surroundings) or DEAD (no face), as ``wp.array(dtype=wp.int32)``."""
    import warp as wp

    from engine.kernels import decimate as kd

    state = wp.empty(len(inc.count), dtype=wp.int32)
    wp.launch(kd.classify_vertices, dim=len(inc.count), inputs=[faces, *inc.inputs, state])
    return state


def compact_faces(faces: Any, n_alive: int) -> Any:
    """The faces that are not removed, in order (a new array of ``n_alive``)."""
    import warp as wp

    from engine.kernels import decimate as kd

    flag = wp.empty(len(faces), dtype=wp.int32)
    slot = wp.empty(len(faces), dtype=wp.int32)
    wp.launch(kd.alive_flags, dim=len(faces), inputs=[faces, flag])
    wp.utils.array_scan(flag, slot, inclusive=False)
    out = wp.empty(n_alive, dtype=wp.vec3i)
    wp.launch(kd.scatter_faces, dim=len(faces), inputs=[faces, slot, out])
    return out


def compact_vertices(pos: Any, faces: Any) -> tuple[Any, Any]:
    """Drop the vertices no face uses (the kept ones keep their order); ``faces`` is remapped in place."""
    import warp as wp

    from engine.kernels import decimate as kd

    with wp.ScopedDevice(pos.device):
        count = wp.zeros(len(pos), dtype=wp.int32)
        wp.launch(kd.count_incidence, dim=len(faces), inputs=[faces, count])
        flag = wp.empty(len(pos), dtype=wp.int32)
        slot = wp.empty(len(pos), dtype=wp.int32)
        wp.launch(kd.used_flags, dim=len(pos), inputs=[count, flag])
        wp.utils.array_scan(flag, slot, inclusive=False)
        n_used = int(slot.numpy()[-1] + flag.numpy()[-1]) if len(pos) else 0  # sync point
        if n_used == len(pos):
            return pos, faces
        out = wp.empty(n_used, dtype=wp.vec3)
        wp.launch(kd.scatter_vertices, dim=len(pos), inputs=[pos, count, slot, out])
        wp.launch(kd.remap_faces, dim=len(faces), inputs=[faces, slot])
    return out, faces


def bbox_centre(pos: Any) -> Any:
    """The centre of the vertices' bounding box as ``wp.vec3d`` (a device reduction; one small copy back)."""
    import numpy as np
    import warp as wp

    from engine.kernels import decimate as kd

    if len(pos) == 0:
        return wp.vec3d(0.0, 0.0, 0.0)
    box = wp.array(np.array([[np.inf] * 3, [-np.inf] * 3], np.float32), dtype=wp.vec3, device=pos.device)
    wp.launch(kd.bounds_kernel, dim=len(pos), inputs=[pos, box], device=pos.device)
    lo, hi = box.numpy().astype(np.float64)  # sync point
    c = 0.5 * (lo + hi)
    return wp.vec3d(float(c[0]), float(c[1]), float(c[2]))
