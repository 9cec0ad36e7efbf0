"""Quadric vertex clustering on the device: the viewing copies' last resort when topology must give way.

A piece of high genus (a trabecular network) cannot be decimated far with the link condition: every tunnel keeps
a ring of faces. To meet a phone's budget anyway, the copy is clustered on a grid (Lindstrom's out-of-core
simplification): one vertex per occupied cell, at the cell's quadric minimum; tunnels narrower than a cell close,
and the copy may lose watertightness. The cell size is searched so that the face count meets the budget closely
(``CLOSE_ENOUGH``): a clustered surface keeps about ``c / h^2`` faces for a cell of size ``h``, so the first
trials rescale the last one by that law, and once the budget is bracketed the next size interpolates the face
count between the bracket's ends (in log scale); a handful of trials suffice where the old bisection took 14 (the
count is not monotone at fine scale, so the search keeps the best trial within the budget). ``Clustering``
prepares a mesh once (bounds, vertex quadrics) for several budgets: the AR copy reuses the phone copy's
preparation, and its search starts from (and is bracketed by) the phone copy's trials. Never used for the print
model.

Piece census (``piece_census``): per connected piece of a device mesh, its volume, faces and vertices, which
tell the viewing copies how many faces a topology-preserving copy needs at least (``Pieces.floor``) and how many
pieces fit a budget as they are (``Pieces.fit``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I
from engine.backend.select import backend_of
from engine.decimation import kernel_specs as K
from engine.decimation import meshops
from engine.surface import devmesh

SEARCH_STEPS = 14  # trial cell sizes at most
CLOSE_ENOUGH = 0.95  # a trial keeping between this share of the budget and the budget ends the search
BRACKET = 1.01  # the search also ends when the sizes over and within the budget are this close
MAX_CELLS = 1 << 21  # cell ids are packed in 21 bits each (engine.decimation.kernels.cluster)


def _cells(pos: Any, lo: Any, h: float) -> tuple[Any, Any, Any, int]:
    """Per vertex its cell id, the vertices sorted by cell and each cell's first sorted slot; and the cell count."""
    be = backend_of(pos)
    n = len(pos)
    keys, order = be.empty(2 * n, np.int64), be.empty(2 * n, np.int32)
    be.launch(K.CELL_KEYS, n, [pos, lo, 1.0 / h, keys, order])
    be.sort_pairs(keys, order, n)
    flag, scan = be.empty(n, np.int32), be.empty(n, np.int32)
    be.launch(K.RUN_STARTS, n, [keys, flag])
    n_cells = be.exclusive_scan(flag, scan)  # sync point
    cell_of = be.empty(n, np.int32)
    start = be.empty(max(n_cells, 1), np.int32)
    be.launch(K.ASSIGN_CELLS, n, [flag, scan, order, cell_of, start])
    return cell_of, order, start, n_cells


def _faces(faces: Any, cell_of: Any) -> tuple[Any, int]:
    """The faces in cells, each set of three cells once (the first face's winding); and their count."""
    be = backend_of(faces)
    nf = len(faces)
    cells = be.empty(nf, VEC3I)
    keys, order = be.empty(2 * nf, np.int64), be.empty(2 * nf, np.int32)
    be.launch(K.FACE_CELLS, nf, [faces, cell_of, cells, keys, order])
    be.sort_pairs(keys, order, nf)
    flag, scan = be.empty(nf, np.int32), be.empty(nf, np.int32)
    be.launch(K.RUN_STARTS, nf, [keys, flag])
    kept = be.exclusive_scan(flag, scan)  # sync point
    out = be.empty(kept, VEC3I)
    be.launch(K.GATHER_FACES, nf, [flag, scan, order, cells, out])
    return out, kept


def _next_size(tried: dict[float, int | None], budget: int, aim: float, h: float, kept: int) -> float | None:
    """The next trial cell size, or None when the budget is bracketed closely (``BRACKET``).

    The bracket is the largest size over the budget and the smallest size above it within the budget; inside it,
    the next size interpolates ``log kept`` against ``log h`` (kept from the ends); without both ends, the last
    trial ``(h, kept)`` is rescaled under ``kept ~ h^-2``."""
    over = [s for s, k in tried.items() if k is None or k > budget]
    lo = max(over) if over else None
    above = [s for s, k in tried.items() if k is not None and k <= budget and (lo is None or s > lo)]
    hi = min(above) if above else None
    if lo is None or hi is None:
        return h * math.sqrt(max(kept, 1) / aim)
    if hi <= lo * BRACKET:
        return None
    k_lo, k_hi = tried[lo] or 4 * budget, max(tried[hi] or 1, 1)
    t = 0.5
    if k_lo > k_hi:
        t = math.log(k_lo / aim) / math.log(k_lo / k_hi)
    t = min(max(t, 0.1), 0.9)  # never creep toward one end
    return lo * (hi / lo) ** t


class Clustering:
    """A device mesh (positions and faces on one ``engine.backend``) prepared for clustering, at one budget or
    several (``copy``): its bounds and vertex quadrics are computed once; face counts already tried are
    remembered."""

    def __init__(self, pos: Any, faces: Any) -> None:
        self.pos, self.faces, self.be = pos, faces, backend_of(pos)
        lo_np, hi_np = meshops.bounds(self.be, pos)
        self.lo = self.be.vector(lo_np, np.float32)
        self.diag = float(np.linalg.norm(hi_np - lo_np)) or 1.0
        self.tried: dict[float, int | None] = {}  # cell size -> faces kept (None: too many cells)
        self._quad: tuple[Any, Any] | None = None
        self._last: tuple[float, Any, Any] | None = None

    def count(self, h: float) -> int | None:
        """Faces kept with cells of size ``h`` (None where the cells would be too many to number)."""
        if h not in self.tried:
            cells = _cells(self.pos, self.lo, h)
            self._last = None
            if cells[3] >= MAX_CELLS:
                self.tried[h] = None
            else:
                out_faces, self.tried[h] = _faces(self.faces, cells[0])
                self._last = (h, cells, out_faces)  # the last trial's arrays: often the one chosen
        return self.tried[h]

    def cell_size(self, max_triangles: int) -> tuple[float, int]:
        """The cell size whose face count is the highest found within ``max_triangles`` (the search stops within
        ``CLOSE_ENOUGH`` of it), and the new trials it took. The sizes tried for other budgets bracket the search
        and start it. Over budget even with the largest cell (a quarter of the diagonal): that cell."""
        aim = max_triangles * (1 + CLOSE_ENOUGH) / 2
        largest = self.diag / 4
        known = [(s, k) for s, k in self.tried.items() if k]
        if known:  # rescale the trial closest to the aim
            size, kept = min(known, key=lambda sk: abs(math.log(sk[1] / aim)))
            h: float | None = size * math.sqrt(kept / aim)
        else:  # first guess: a box-like surface
            h = self.diag * math.sqrt(2.0 / aim)
        trials = 0
        while h is not None and trials < SEARCH_STEPS:
            fits = [k for k in self.tried.values() if k is not None and k <= max_triangles]
            if fits and max(fits) >= CLOSE_ENOUGH * max_triangles:
                break
            h = min(max(h, self.diag * 1e-6), largest)
            if h in self.tried:
                break
            trials += 1
            kept = self.count(h)
            if h >= largest and (kept is None or kept > max_triangles):
                break
            h = _next_size(self.tried, max_triangles, aim, h, kept if kept is not None else 4 * max_triangles)
        fits = [(k, -s) for s, k in self.tried.items() if k is not None and k <= max_triangles]
        return (-max(fits)[1] if fits else largest), trials

    def copy(self, max_triangles: int) -> tuple[Any, Any, dict[str, Any]]:
        """The clustered copy within ``max_triangles`` faces (as close below as the cell size allows): new device
        arrays and a report (``cell_mm``, ``faces``, ``input_faces``, ``trials``: new cell sizes tried, ``seconds``)."""
        from engine.decimation.phases import vertex_quadrics

        t0 = time.perf_counter()
        be = self.be
        h, trials = self.cell_size(max_triangles)
        if self._last is not None and self._last[0] == h:
            _, (cell_of, order, start, n_cells), out_faces = self._last
        else:
            cell_of, order, start, n_cells = _cells(self.pos, self.lo, h)
            out_faces = _faces(self.faces, cell_of)[0]
        self._last = None  # compact_vertices remaps the faces in place
        kept = len(out_faces)
        if self._quad is None:
            _, _, origin, quad = vertex_quadrics(self.pos, self.faces)
            self._quad = (origin, quad)
        origin, quad = self._quad
        cell_pos = be.empty(max(n_cells, 1), VEC3F)
        inputs = [self.pos, quad, order, start, len(self.pos), n_cells, origin, cell_pos]
        be.launch(K.CELL_POSITIONS, n_cells, inputs)
        out_pos, out_faces = devmesh.compact_vertices(be.view(cell_pos, 0, n_cells), out_faces)
        info = {
            "cell_mm": h,
            "faces": kept,
            "input_faces": len(self.faces),
            "trials": trials,
            "seconds": time.perf_counter() - t0,
        }
        return out_pos, out_faces, info


def cluster_device(pos: Any, faces: Any, max_triangles: int) -> tuple[Any, Any, dict[str, Any]]:
    """Cluster a device mesh down to at most ``max_triangles`` faces (as close below it as the cell size allows).

    Returns new device arrays (positions and faces, on the mesh's backend) and ``Clustering.copy``'s report.
    """
    return Clustering(pos, faces).copy(max_triangles)


@dataclass
class Pieces:
    """The connected pieces of a device mesh, largest volume first (ties: the piece of the smaller vertex index
    first, the order in which ``remove_islands_device(keep_largest=...)`` keeps them): volume (mm^3), faces and
    vertices of each."""

    volume: np.ndarray
    faces: np.ndarray
    vertices: np.ndarray

    def __len__(self) -> int:
        return len(self.volume)

    def floor(self, n: int) -> int:
        """The fewest faces the ``n`` largest pieces can keep under the topology guard, when closed: a closed
        piece of Euler characteristic X = V - F / 2 keeps at least 8 - 2 X = 4 + 4 genus faces."""
        v, f = self.vertices[:n].astype(np.int64), self.faces[:n].astype(np.int64)
        return int(np.maximum(8 - 2 * (v - f // 2), 4).sum())

    def fit(self, budget: int) -> int:
        """How many of the largest pieces fit within ``budget`` faces as they are now."""
        return int(np.searchsorted(np.cumsum(self.faces, dtype=np.int64), budget, side="right"))


def piece_census(pos: Any, faces: Any) -> Pieces:
    """Count the pieces of a device mesh (``engine.surface.islands.measure_pieces``, and the used vertices of each)."""
    from engine.surface.islands import measure_pieces

    be = backend_of(pos)
    nv, nf = len(pos), len(faces)
    label, roots, counts, volume = measure_pieces(pos, faces)
    used = be.zeros(nv, np.int32)
    nverts = be.zeros(nv, np.int32)
    if nf:
        be.launch(K.COUNT_INCIDENCE, nf, [faces, used])
        be.launch(K.PIECE_VERTICES, nv, [used, label, nverts])
    order = np.argsort(-volume, kind="stable")
    return Pieces(volume[order], counts[roots][order], be.to_host(nverts)[roots][order])
