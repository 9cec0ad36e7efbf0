"""Exporters: ``Mesh -> bytes`` functions in a registry (trimesh style).

Each takes ``(vertices_zyx_mm, faces, ...)`` in the engine's conventions (see ``engine.types.Mesh``) and returns the
file's bytes: "stl" (mm, x/y/z), "glb" (glTF 2.0 binary, metres, +Y up) and "draco_glb" (the same with
``KHR_draco_mesh_compression``).
"""

from __future__ import annotations

from engine.export.draco import to_draco_glb
from engine.export.glb import to_glb
from engine.export.stl import to_stl

EXPORTERS = {"stl": to_stl, "glb": to_glb, "draco_glb": to_draco_glb}

__all__ = ["EXPORTERS", "to_draco_glb", "to_glb", "to_stl"]
