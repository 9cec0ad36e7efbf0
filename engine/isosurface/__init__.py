"""The paper's step 2, Marching Cubes 33: the host wrapper (``mc33``: ``marching_cubes_33`` on numpy,
``extract_isosurface`` on a device volume) over the slab pass (``slabs``: classify blocks -> count -> scan -> emit,
kernels in ``engine.isosurface.kernels``: Warp's ``mc33.py`` and OpenCL's ``mc33.cl``, named in ``kernel_specs``
and launched through ``engine.backend``; tables in ``mc33_tables`` with their generator ``_make_mc33_tables``
beside them, uploaded to either backend from that one source), and the volume stages streamed within a memory
budget (``stream``, fed by ``feed``).

Public names load lazily (``engine._lazy``): ``from engine.isosurface import marching_cubes_33``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.isosurface.mc33 import extract_isosurface, marching_cubes_33
    from engine.isosurface.slabs import TIE_TAU, join_parts
    from engine.isosurface.stats import IsosurfaceStats
    from engine.isosurface.stream import StreamResult, stream_surface

__all__ = [
    "TIE_TAU",
    "IsosurfaceStats",
    "StreamResult",
    "extract_isosurface",
    "join_parts",
    "marching_cubes_33",
    "stream_surface",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "IsosurfaceStats": ".stats",
        "TIE_TAU": ".slabs",
        "extract_isosurface": ".mc33",
        "join_parts": ".slabs",
        "marching_cubes_33": ".mc33",
        "StreamResult": ".stream",
        "stream_surface": ".stream",
    },
)
