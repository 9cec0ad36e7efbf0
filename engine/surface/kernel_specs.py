"""The named kernels of the surface stages (``engine.backend.Kernel``), each written twice: the Warp kernels of
``kernels/*.py`` and the OpenCL C of ``kernels/*.cl`` (same names, same arguments, same arithmetic in the same
order), launched by the one host code of ``devmesh``, ``islands``, ``smooth`` and ``normals``."""

from __future__ import annotations

from engine.backend.base import Kernel

_W = "engine.surface.kernels"
_CL = "engine.surface.kernels"


def _spec(module: str, warp: str, opencl: str | None = None) -> Kernel:
    return Kernel(f"surface.{module}.{warp}", f"{_W}.{module}:{warp}", f"{_CL}:{module}.cl:{opencl or warp}")


# topology: stars (CSR, sorted per vertex) and vertex classes
COUNT_INCIDENCE = _spec("topology", "count_incidence")
FILL_INCIDENCE = _spec("topology", "fill_incidence")
SORT_INCIDENCE = _spec("topology", "sort_incidence")
CLASSIFY = _spec("topology", "classify_vertices")
COUNT_CLASSES = _spec("topology", "count_classes")

# compaction: removed faces and unused vertices dropped, order kept; the bounding box
ALIVE_FLAGS = _spec("compaction", "alive_flags")
SCATTER_FACES = _spec("compaction", "scatter_faces")
USED_FLAGS = _spec("compaction", "used_flags")
SCATTER_VERTICES = _spec("compaction", "scatter_vertices")
REMAP_FACES = _spec("compaction", "remap_faces")
BOUNDS = _spec("compaction", "bounds_kernel")

# measures: the edge census, face sums, connected pieces
EDGE_CENSUS = _spec("measures", "edge_census")
FACE_MEASURES = _spec("measures", "face_measures")
RUN_SUMS = _spec("measures", "run_sums")
OWN_LABELS = _spec("measures", "own_labels")
HOOK_LABELS = _spec("measures", "hook_labels")
JUMP_LABELS = _spec("measures", "jump_labels")
COUNT_ROOTS = _spec("measures", "count_roots")
PIECE_VOLUMES = _spec("measures", "piece_volumes")
DROP_PIECES = _spec("measures", "drop_pieces")

# smoothing and normals
NEIGHBOUR_MEAN = _spec("smoothing", "star_neighbour_mean_kernel", "star_neighbour_mean")
STAR_NORMALS = _spec("smoothing", "star_normals_kernel", "star_normals")
FIXED = _spec("smoothing", "fixed_from_classes")
REJECT = _spec("smoothing", "reject_kernel", "reject_moves")
ACCEPT = _spec("smoothing", "accept_kernel", "accept_moves")
VIOLATIONS = _spec("smoothing", "violation_kernel", "find_violations")
REVERT = _spec("smoothing", "revert_kernel", "revert_moves")
