"""MeshLab's quadric-error decimation (through pymeshlab): the reference the Warp path is measured against
(``decimate_mesh(..., method="meshlab")``, ``benchmarks/decimate.py``).

The paper's remeshing step: Garland-Heckbert quadric edge collapses down to a *reduction factor* (the fraction
of faces kept). MeshLab's implementation is used with

* ``preservetopology``: a collapse is done only if it passes the link condition, so a watertight 2-manifold
  input stays watertight and 2-manifold, with the same components and Euler characteristic (a plain collapse
  library such as fast-simplification pinches sheets onto one edge and leaves duplicate fins on bone surfaces);
* ``preserveboundary``: open borders keep their vertices;
* ``preservenormal``: a collapse that would flip a face is rejected.

Where the link condition stops the collapses above the target (tiny closed pieces cannot shrink below a
tetrahedron), the result keeps more faces than asked and ``info["limited_by_watertightness"]`` says so.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.surface.meshcheck import edge_report

PARALLEL_MIN_FACES = 400_000
MIN_FACES_PER_WORKER = 100_000


def _workers(n_faces: int, workers: int | None) -> int:
    if workers is None:
        usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        workers = min(16, usable) if n_faces >= PARALLEL_MIN_FACES else 1
    return max(1, min(int(workers), n_faces // MIN_FACES_PER_WORKER))


def _collapse(
    pts: np.ndarray, faces: np.ndarray, target: int, preserve_topology: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """MeshLab's quadric edge collapse down to ``target`` faces (with the link condition unless told otherwise);
    unreferenced points are dropped."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts, face_matrix=faces))
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target),
        preservetopology=preserve_topology,
        preserveboundary=True,
        boundaryweight=1.0,
        preservenormal=True,
        optimalplacement=True,
        planarquadric=False,
        qualitythr=0.3,
        autoclean=False,  # its duplicate-vertex merge would pinch two vertices that merely coincide
    )
    mesh = ms.current_mesh()
    out_pts = np.asarray(mesh.vertex_matrix(), dtype=np.float64)
    out_faces = np.asarray(mesh.face_matrix(), dtype=np.int32)
    used = np.unique(out_faces)
    if len(used) == len(out_pts):
        return out_pts, out_faces
    return out_pts[used], np.searchsorted(used, out_faces).astype(np.int32)


@dataclass(frozen=True)
class Slab:
    """A piece of the input mesh: its points, faces (local indices) and each point's index in the input."""

    points: np.ndarray
    faces: np.ndarray
    global_ids: np.ndarray


def _collapse_in_slabs(
    pts: np.ndarray, faces: np.ndarray, target: int, workers: int, closed: bool
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Decimate z slabs of the mesh in parallel processes; the cut borders are preserved, so the stitched result
    is closed and 2-manifold where the input was (the border vertices come back unmoved and are joined)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    cz = pts[faces].mean(axis=1)[:, 2]
    cuts = np.quantile(cz, np.linspace(0, 1, workers + 1)[1:-1])
    slab = np.searchsorted(cuts, cz)
    slabs, targets = [], []
    for k in range(workers):
        sub = faces[slab == k]
        used, inverse = np.unique(sub.ravel(), return_inverse=True)
        slabs.append(Slab(pts[used], inverse.reshape(-1, 3).astype(np.int32), used))
        targets.append(max(1, round(target * len(sub) / len(faces))))
    # fork where available: the children run only MeshLab (never CUDA, so a CUDA context in the parent is safe)
    # and need not re-import the caller's main module as spawn would
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        parts = list(pool.map(_collapse, [s.points for s in slabs], [s.faces for s in slabs], targets))
    return _stitch_slabs(parts, slabs, closed)


def _stitch_slabs(
    parts: list[tuple[np.ndarray, np.ndarray]], slabs: list[Slab], closed: bool
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Join decimated slabs on their cut borders.

    Only a slab's border vertices (on its boundary edges: the cut, and any border of the input) are joined, to
    their input vertex, by exact coordinates; every other vertex stays its own, even where two coincide. A slab
    that did not return each border vertex exactly once, or (closed input) owns a face on an edge of the result
    that is not in exactly two faces, is replaced by its original faces, which join through their input indices,
    until none is left: with every slab whole the result is the input itself. Returns points, faces and the
    slabs kept whole.
    """
    borders = [_border_vertices(s.faces, len(s.points)) for s in slabs]
    gids = np.unique(np.concatenate([s.global_ids[b] for s, b in zip(slabs, borders, strict=True)]))
    slots = [np.searchsorted(gids, s.global_ids[b]) for s, b in zip(slabs, borders, strict=True)]
    border_pts = np.zeros((len(gids), 3))
    for s, b, slot in zip(slabs, borders, slots, strict=True):
        border_pts[slot] = s.points[b]
    pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    kept_whole: list[int] = []
    for k, ((p, f), b, slot) in enumerate(zip(parts, borders, slots, strict=True)):
        where = _match_points(p, border_pts[slot], slot)
        if where is None:
            kept_whole.append(k)
        pieces.append((p, f, where) if where is not None else _whole(slabs[k], b, slot))
    while True:
        merged, faces_out, owner = _assemble(border_pts, pieces)
        bad = [k for k in _defective_slabs(faces_out, owner, len(merged)) if k not in kept_whole] if closed else []
        if not bad:
            return merged, faces_out, sorted(kept_whole)
        for k in bad:
            pieces[k] = _whole(slabs[k], borders[k], slots[k])
            kept_whole.append(k)


def _border_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Vertices on edges that are in one face only."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    key = np.minimum(e[:, 0], e[:, 1]) * n_vertices + np.maximum(e[:, 0], e[:, 1])
    _, first, counts = np.unique(key, return_index=True, return_counts=True)
    return np.unique(e[first[counts == 1]])


def _whole(slab: Slab, border: np.ndarray, slot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    where = np.full(len(slab.points), -1, np.int64)
    where[border] = slot
    return slab.points, slab.faces, where


def _match_points(points: np.ndarray, wanted: np.ndarray, slot: np.ndarray) -> np.ndarray | None:
    """Per point, the slot of the wanted point it equals exactly (-1 for none); None unless every wanted point is
    found exactly once."""
    where = np.full(len(points), -1, np.int64)
    if len(wanted) == 0:
        return where
    hw, hp = _hash_rows(wanted), _hash_rows(points)
    order = np.argsort(hw)
    pos = np.minimum(np.searchsorted(hw[order], hp), len(wanted) - 1)
    cand = order[pos]
    hit = (hw[cand] == hp) & (wanted[cand] == points).all(axis=1)
    if np.count_nonzero(hit) != len(wanted) or len(np.unique(cand[hit])) != len(wanted):
        return None
    where[hit] = slot[cand[hit]]
    return where


def _hash_rows(points: np.ndarray) -> np.ndarray:
    """A 64-bit hash of the exact bits of each (x, y, z) float64 row."""
    bits = np.ascontiguousarray(points, dtype=np.float64).view(np.uint64).reshape(-1, 3)
    with np.errstate(over="ignore"):
        key = (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F))
        key ^= bits[:, 2] * np.uint64(0x165667B19E3779F9)
    return key


def _assemble(
    border_pts: np.ndarray, pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One mesh from the pieces: the shared border points first, then each piece's own points; and each face's
    piece."""
    out_pts, out_faces, owner = [border_pts], [], []
    n = len(border_pts)
    for k, (p, f, where) in enumerate(pieces):
        own = where < 0
        index = where.copy()
        index[own] = n + np.arange(np.count_nonzero(own))
        n += np.count_nonzero(own)
        out_pts.append(p[own])
        out_faces.append(index[f])
        owner.append(np.full(len(f), k, np.int32))
    return np.concatenate(out_pts), np.concatenate(out_faces).astype(np.int32), np.concatenate(owner)


def _defective_slabs(faces: np.ndarray, owner: np.ndarray, n_vertices: int) -> list[int]:
    """Slabs owning a face on an edge that is not shared by exactly two faces."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    key = np.minimum(e[:, 0], e[:, 1]) * n_vertices + np.maximum(e[:, 0], e[:, 1])
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    bad_face = (counts[inverse.reshape(-1)] != 2).reshape(3, -1).any(axis=0)
    return sorted(set(owner[bad_face].tolist()))


def collapse_meshlab(
    pts: np.ndarray, faces: np.ndarray, target: int, closed: bool, workers: int | None = None
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """MeshLab's collapse of a compact mesh (``pts`` (x, y, z) float64) to ``target`` faces, in z slabs over
    processes for large meshes; a closed input that would come back open is returned unchanged.

    Returns float32 (z, y, x) vertices, int32 faces and the report entries of this path.
    """
    if importlib.util.find_spec("pymeshlab") is None:  # found, not imported: the slab processes import it
        # the `reference` extra: GPL-3 and 100 MB, not in the base install
        raise ImportError("MeshLab's decimation needs pymeshlab: pip install 'bonemesh[reference]'")
    info: dict[str, Any] = {
        "method": "MeshLab quadric edge collapse (preservetopology, preserveboundary, preservenormal)"
    }
    n_workers = _workers(len(faces), workers)
    info["workers"] = n_workers
    if n_workers > 1:
        out_pts, out_faces, kept_whole = _collapse_in_slabs(pts, faces.astype(np.int32), target, n_workers, closed)
        info["slabs_kept_whole"] = kept_whole
    else:
        out_pts, out_faces = _collapse(pts, faces.astype(np.int32), target)
    after = edge_report(out_faces, len(out_pts))
    if closed and (after["boundary_edges"] or after["nonmanifold_edges"]):  # keep the input rather than break it
        out_pts, out_faces = pts, faces.astype(np.int32)
    return np.ascontiguousarray(out_pts[:, ::-1], dtype=np.float32), out_faces, info
