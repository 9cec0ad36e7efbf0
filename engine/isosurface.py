"""Public isosurface API: ``from engine.isosurface import marching_cubes_33``."""

from engine.stages.isosurface import IsosurfaceStats, extract_isosurface, marching_cubes_33

__all__ = ["IsosurfaceStats", "extract_isosurface", "marching_cubes_33"]
