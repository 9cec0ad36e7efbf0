"""bonemesh engine: arrays in, meshes out.

Public API (loaded lazily through ``engine._lazy``, so ``import engine.params`` never imports Warp): ``reconstruct``,
``write_outputs``, ``Reconstruction``, ``ReconParams``, ``Budget``, ``Volume``, ``Mesh``, ``load_volume``,
``marching_cubes_33``.

The floor plan, at a glance:

* the ground floor (12 modules): the contracts (``params``, ``types``, ``errors``, ``report``: the report's declared
  type), the budget and the device specs (``budget``, ``device``), and the shared basics of several stages
  (``level``: the iso level; ``orient``: the patient frame; ``staging``: page-locked host buffers);
* ``backend``: the one interface the device stages run on (Warp or OpenCL), device memory measured;
* one package per stage of the paper, each with its kernels in a ``kernels`` folder (``volume``, ``isosurface``,
  ``decimation``, ``surface``), and the product's own stages: ``labels`` (a model per label) and ``defect``;
* ``io`` (files -> Volume) and ``export`` (Mesh -> bytes, and ``export.files``: the registry of output files);
* ``job``: a job from its spec to its files (``spec``, ``runtime``, ``run``; the ``pipeline`` and its ``plans``,
  ``outputs``, ``reorient``, ``warmup``, ``progress``), the one public face of the worker;
* ``cli``: the ``bonemesh`` commands (``args``, ``defect``, ``orient``, ``sweep``), thin callers of ``job``;
* ``paper``: the paper's sweep and metrics; ``data``: the bundled scan and the phantom.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.budget import Budget
    from engine.io import load_volume
    from engine.isosurface import marching_cubes_33
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import Reconstruction, reconstruct
    from engine.params import ReconParams
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
        "Reconstruction": "engine.job.pipeline",
        "Volume": "engine.types",
        "load_volume": "engine.io",
        "marching_cubes_33": "engine.isosurface",
        "reconstruct": "engine.job.pipeline",
        "write_outputs": "engine.job.outputs",
    },
)
