"""Exporters: ``Mesh -> bytes`` functions in a registry (trimesh style).

Each takes ``(vertices_zyx_mm, faces, ...)`` in the engine's conventions (see ``engine.types.Mesh``) and returns the
file's bytes. ``EXPORTERS`` maps each format to its exporter ("stl": mm, x/y/z; "glb": glTF 2.0 binary, metres,
+Y up; "draco_glb": the same with ``KHR_draco_mesh_compression``; "meshopt_glb", "usdz", "preview_png",
"encapsulated_stl"); it is read from the registry of output files (``engine.export.files.FILES``), which names
every file a job writes and the exporter of its format.

Public names load lazily (``engine._lazy``): importing ``engine.export`` (or ``engine.export.files``, as the API
does) loads no exporter, DracoPy or numpy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.export.draco import to_draco_glb
    from engine.export.files import EXPORTERS, FILES
    from engine.export.glb import to_glb
    from engine.export.stl import to_stl

__all__ = ["EXPORTERS", "FILES", "to_draco_glb", "to_glb", "to_stl"]
__getattr__, __dir__ = attach(
    __name__,
    {
        "EXPORTERS": ".files",
        "FILES": ".files",
        "to_draco_glb": ".draco",
        "to_glb": ".glb",
        "to_stl": ".stl",
    },
)
