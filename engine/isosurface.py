"""Public isosurface API: ``from engine.isosurface import marching_cubes_33``."""

from engine.stages.isosurface import IsosurfaceStats, marching_cubes_33

__all__ = ["IsosurfaceStats", "marching_cubes_33"]
