"""The named kernels of the decimation (``engine.backend.Kernel``), each written twice: the Warp kernels of this
package's modules and their OpenCL C twins in ``kernels/*.cl``: ``price.cl`` and ``claims.cl`` (the pass, sharing
``pass.cl``), ``mesh.cl`` (the quadrics' compaction, locked vertices), ``cluster.cl`` and ``tiles.cl``; launched with
the same arguments by the one host code (``engine.decimation.phases`` and the modules beside it). The device mesh's
stars, vertex classes, compaction and bounds are the surface package's kernels (``engine.surface.kernel_specs``,
both backends). Importing this module loads neither Warp nor PyOpenCL."""

from __future__ import annotations

from engine.backend.base import Kernel
from engine.surface import kernel_specs as surface

_K = "engine.decimation.kernels"
_PRICE = f"{_K}:price.cl"
_CLAIMS = f"{_K}:claims.cl"
_MESH = f"{_K}:mesh.cl"


def _k(name: str, warp: str, cl_file: str) -> Kernel:
    attr = warp.rpartition(":")[2]
    return Kernel(f"decimation.{name}", warp, f"{cl_file}:{attr}")


# the device mesh (stars, vertex classes, compaction, bounds): the surface package's kernels
COUNT_INCIDENCE = surface.COUNT_INCIDENCE
FILL_INCIDENCE = surface.FILL_INCIDENCE
SORT_INCIDENCE = surface.SORT_INCIDENCE
CLASSIFY = surface.CLASSIFY
ALIVE_FLAGS = surface.ALIVE_FLAGS
SCATTER_FACES = surface.SCATTER_FACES
USED_FLAGS = surface.USED_FLAGS
SCATTER_VERTICES = surface.SCATTER_VERTICES
REMAP_FACES = surface.REMAP_FACES
BOUNDS = surface.BOUNDS
SCATTER_KEPT = _k("scatter_kept", f"{_K}.quadrics:scatter_kept", _MESH)
LOCK_VERTICES = _k("lock_vertices", f"{_K}.collapse:lock_vertices", _MESH)

# the pass
VERTEX_QUADRICS = _k("vertex_quadrics", f"{_K}.quadrics:vertex_quadrics", _PRICE)
EDGE_COSTS = _k("edge_costs", f"{_K}.costs:edge_costs", _PRICE)
COST_HISTOGRAM = _k("cost_histogram", f"{_K}.costs:cost_histogram", _PRICE)
SELECT_CANDIDATES = _k("select_candidates", f"{_K}.costs:select_candidates", _PRICE)
CHECK_CANDIDATES = _k("check_candidates", f"{_K}.guards:check_candidates", _PRICE)
CLAIM_STARS = _k("claim_stars", f"{_K}.claims:claim_stars", _CLAIMS)
SETTLE_CLAIMS = _k("settle_claims", f"{_K}.claims:settle_claims", _CLAIMS)
TAKE_STARS = _k("take_stars", f"{_K}.claims:take_stars", _CLAIMS)
RELEASE_CLAIMS = _k("release_claims", f"{_K}.claims:release_claims", _CLAIMS)
WINNER_HISTOGRAM = _k("winner_histogram", f"{_K}.claims:winner_histogram", _CLAIMS)
TRIM_WINNERS = _k("trim_winners", f"{_K}.claims:trim_winners", _CLAIMS)
CHEAPEST_TRIMMED = _k("cheapest_trimmed", f"{_K}.claims:cheapest_trimmed", _CLAIMS)
RESTORE_CHEAPEST = _k("restore_cheapest", f"{_K}.claims:restore_cheapest", _CLAIMS)
APPLY_COLLAPSES = _k("apply_collapses", f"{_K}.collapse:apply_collapses", _CLAIMS)

NO_KEY = 0x7FFFFFFF  # the kernels' NO_KEY (both files)
CLAIM_FREE = 0x7FFFFFFFFFFFFFFF  # the kernels' CLAIM_FREE (both files)

# clustering and the piece census
_CLUSTER = f"{_K}:cluster.cl"
CELL_KEYS = _k("cell_keys", f"{_K}.cluster:cell_keys", _CLUSTER)
ASSIGN_CELLS = _k("assign_cells", f"{_K}.cluster:assign_cells", _CLUSTER)
FACE_CELLS = _k("face_cells", f"{_K}.cluster:face_cells", _CLUSTER)
RUN_STARTS = _k("run_starts", f"{_K}.cluster:run_starts", _CLUSTER)
GATHER_FACES = _k("gather_faces", f"{_K}.cluster:gather_faces", _CLUSTER)
CELL_POSITIONS = _k("cell_positions", f"{_K}.cluster:cell_positions", _CLUSTER)
PIECE_VERTICES = _k("piece_vertices", f"{_K}.cluster:piece_vertices", _CLUSTER)

# decimating piece by piece (groups of slabs, seams, tiles)
_TILES = f"{_K}:tiles.cl"
LOCALIZE_FACES = _k("localize_faces", f"{_K}.tiles:localize_faces", _TILES)
GLOBALIZE_FACES = _k("globalize_faces", f"{_K}.tiles:globalize_faces", _TILES)
ADD_QUADRICS = _k("add_quadrics", f"{_K}.tiles:add_quadrics", _TILES)
SEAM_FLAGS = _k("seam_flags", f"{_K}.tiles:seam_flags", _TILES)
RANGE_FLAGS = _k("range_flags", f"{_K}.tiles:range_flags", _TILES)
FACE_SAMPLE = _k("face_sample", f"{_K}.tiles:face_sample", _TILES)
MARK_USED = _k("mark_used", f"{_K}.tiles:mark_used", _TILES)
SPLIT_FACES = _k("split_faces", f"{_K}.tiles:split_faces", _TILES)
GATHER_SEAM = _k("gather_seam", f"{_K}.tiles:gather_seam", _TILES)
NEW_VERTEX_FLAGS = _k("new_vertex_flags", f"{_K}.tiles:new_vertex_flags", _TILES)
JOIN_SEAM = _k("join_seam", f"{_K}.tiles:join_seam", _TILES)
