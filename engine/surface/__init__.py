"""The mesh after decimation: its topology and compaction on the device (``devmesh``), its checks (``meshcheck``
on the host, ``mesh_stats_device`` on the device), speck removal (``islands``), the paper's step 4,
surface-preserving Laplacian smoothing (``smooth``), and vertex normals (``normals``). The host code is written once
over ``engine.backend`` (the backend the arrays live on: Warp, or OpenCL through PyOpenCL); the kernels, named in
``engine.surface.kernel_specs``, are in ``engine.surface.kernels``: Warp (``*.py``) with OpenCL C twins (``*.cl``).
The other packages (decimation, the exporters' print check, the pipeline) use these public functions.

Public names load lazily (``engine._lazy``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.surface.devmesh import (
        Incidence,
        bounds,
        compact_faces,
        compact_vertices,
        component_labels_device,
        mesh_stats_device,
        on_device,
    )
    from engine.surface.islands import compact_mesh, measure_pieces, remove_islands, remove_islands_device
    from engine.surface.meshcheck import (
        component_labels,
        edge_report,
        face_normals,
        face_volumes,
        is_closed_manifold,
        mesh_stats,
        validate_mesh,
    )
    from engine.surface.normals import normals_device, vertex_normals
    from engine.surface.smooth import smooth_device, smooth_mesh, unique_edges

__all__ = [
    "Incidence",
    "bounds",
    "compact_faces",
    "compact_mesh",
    "compact_vertices",
    "component_labels",
    "component_labels_device",
    "edge_report",
    "face_normals",
    "face_volumes",
    "is_closed_manifold",
    "measure_pieces",
    "mesh_stats",
    "mesh_stats_device",
    "normals_device",
    "on_device",
    "remove_islands",
    "remove_islands_device",
    "smooth_device",
    "smooth_mesh",
    "unique_edges",
    "validate_mesh",
    "vertex_normals",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "Incidence": ".devmesh",
        "bounds": ".devmesh",
        "compact_faces": ".devmesh",
        "compact_vertices": ".devmesh",
        "component_labels_device": ".devmesh",
        "mesh_stats_device": ".devmesh",
        "on_device": ".devmesh",
        "compact_mesh": ".islands",
        "measure_pieces": ".islands",
        "remove_islands": ".islands",
        "remove_islands_device": ".islands",
        "component_labels": ".meshcheck",
        "edge_report": ".meshcheck",
        "face_normals": ".meshcheck",
        "face_volumes": ".meshcheck",
        "is_closed_manifold": ".meshcheck",
        "mesh_stats": ".meshcheck",
        "validate_mesh": ".meshcheck",
        "normals_device": ".normals",
        "vertex_normals": ".normals",
        "smooth_device": ".smooth",
        "smooth_mesh": ".smooth",
        "unique_edges": ".smooth",
    },
)
