"""Exporters: ``Mesh -> bytes`` functions in a registry (trimesh style)."""

from __future__ import annotations

from engine.export.stl import to_stl

EXPORTERS = {"stl": to_stl}

__all__ = ["EXPORTERS", "to_stl"]
