"""The paper's step 3, quadric-error decimation, under one roof (meshoptimizer's simplifier family):

* ``passes``: the pass loop on the device, running the named phases of ``phases`` (update adjacency, price, rank,
  guard, claim, trim, perform, compact), written once over the backend interface (``engine.backend``: Warp or
  OpenCL, the backend found from the arrays): Warp kernels in ``engine.decimation.kernels`` split by concern, their
  OpenCL C twins beside them (``kernels/*.cl``), both named in ``kernel_specs``; the device mesh's stars, classes
  and compaction in ``meshops``;
  ``arrays``: the numpy entry point with a full report;
* within a memory budget: ``groups`` (groups of slabs while the volume streams), ``seams`` (across their borders),
  ``tiles`` (tiled rounds, on the device or from the host) and ``pieces`` (a flagged piece decimated beside the
  rest of the mesh);
* ``viewing``: the phone and AR copies of a model, with ``cluster`` (quadric vertex clustering) as the last resort;
* ``meshlab``: MeshLab's collapse, the reference the Warp path is measured against; ``probe``: one pricing pass of
  the kernels, for tests and diagnosis.

Public names load lazily (``engine._lazy``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.decimation.arrays import decimate_mesh
    from engine.decimation.cluster import Clustering, Pieces, cluster_device, piece_census
    from engine.decimation.groups import GroupDecimator, finish_groups
    from engine.decimation.passes import (
        Decimated,
        DecimationStats,
        decimate_carrying,
        decimate_device,
    )
    from engine.decimation.phases import vertex_quadrics
    from engine.decimation.probe import price_edges
    from engine.decimation.tiles import decimate_within
    from engine.decimation.viewing import viewing_copies, viewing_copy

__all__ = [
    "Clustering",
    "Decimated",
    "DecimationStats",
    "GroupDecimator",
    "Pieces",
    "cluster_device",
    "decimate_carrying",
    "decimate_device",
    "decimate_mesh",
    "decimate_within",
    "finish_groups",
    "piece_census",
    "price_edges",
    "vertex_quadrics",
    "viewing_copies",
    "viewing_copy",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "decimate_mesh": ".arrays",
        "Clustering": ".cluster",
        "Pieces": ".cluster",
        "cluster_device": ".cluster",
        "piece_census": ".cluster",
        "GroupDecimator": ".groups",
        "finish_groups": ".groups",
        "Decimated": ".passes",
        "DecimationStats": ".passes",
        "decimate_carrying": ".passes",
        "decimate_device": ".passes",
        "vertex_quadrics": ".phases",
        "price_edges": ".probe",
        "decimate_within": ".tiles",
        "viewing_copies": ".viewing",
        "viewing_copy": ".viewing",
    },
)
