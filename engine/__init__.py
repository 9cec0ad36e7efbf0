"""bonemesh engine: arrays in, meshes out.

Public API (loaded lazily, so ``import engine.params`` never imports Warp): ``reconstruct``, ``write_outputs``,
``Reconstruction``, ``ReconParams``, ``Volume``, ``Mesh``, ``load_volume``, ``marching_cubes_33``.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "Mesh",
    "ReconParams",
    "Reconstruction",
    "Volume",
    "load_volume",
    "marching_cubes_33",
    "reconstruct",
    "write_outputs",
]

_WHERE = {
    "reconstruct": "engine.pipeline",
    "write_outputs": "engine.outputs",
    "Reconstruction": "engine.pipeline",
    "ReconParams": "engine.params",
    "Volume": "engine.types",
    "Mesh": "engine.types",
    "load_volume": "engine.io",
    "marching_cubes_33": "engine.isosurface",
}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'engine' has no attribute {name!r}")
