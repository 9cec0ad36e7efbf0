"""bonemesh engine: arrays in, meshes out.

Public API (loaded lazily through ``engine._lazy``, so ``import engine.params`` never imports Warp): ``reconstruct``,
``write_outputs``, ``Reconstruction``, ``ReconParams``, ``Budget``, ``Volume``, ``Mesh``, ``load_volume``,
``marching_cubes_33``.

The floor plan: the contracts on the ground floor (``params``, ``types``, ``errors``, ``budget``, ``device``); one
package per stage of the paper, each with its kernels in a ``kernels`` folder (``volume``, ``isosurface``,
``decimation``, ``surface``); ``export`` (Mesh -> bytes, and ``export.files``: the registry of output files) and
``io`` (files -> Volume); ``pipeline`` and its ``plans``, ``outputs``, and ``report`` (the report's declared type);
and the paper's sweep and metrics in ``paper``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.budget import Budget
    from engine.io import load_volume
    from engine.isosurface import marching_cubes_33
    from engine.outputs import write_outputs
    from engine.params import ReconParams
    from engine.pipeline import Reconstruction, reconstruct
    from engine.types import Mesh, Volume

__all__ = [
    "Budget",
    "Mesh",
    "ReconParams",
    "Reconstruction",
    "Volume",
    "load_volume",
    "marching_cubes_33",
    "reconstruct",
    "write_outputs",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "Budget": "engine.budget",
        "Mesh": "engine.types",
        "ReconParams": "engine.params",
        "Reconstruction": "engine.pipeline",
        "Volume": "engine.types",
        "load_volume": "engine.io",
        "marching_cubes_33": "engine.isosurface",
        "reconstruct": "engine.pipeline",
        "write_outputs": "engine.outputs",
    },
)
