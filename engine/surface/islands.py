"""Remove small connected pieces ("islands") of a mesh: noise specks, loose fragments, floating debris."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from engine.surface.meshcheck import component_labels, face_volumes, validate_mesh

PIECE_RUN = 32  # faces per thread when the pieces' volumes are summed (one atomic per change of piece)


def compact_mesh(
    verts: npt.NDArray[Any], faces: npt.NDArray[Any]
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Drop unused vertices and remap the faces; the kept vertices keep their order."""
    used = np.zeros(len(verts), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used, dtype=np.int64) - 1
    return (
        np.ascontiguousarray(verts[used], dtype=np.float32),
        remap[faces].astype(np.int32).reshape(-1, 3),
    )


def _check_limits(min_volume_mm3: float | None, keep_largest: int | None) -> None:
    if min_volume_mm3 is not None and not (np.isfinite(min_volume_mm3) and min_volume_mm3 >= 0):
        raise ValueError(f"min_volume_mm3 must be a finite number >= 0, got {min_volume_mm3}")
    if keep_largest is not None and (
        isinstance(keep_largest, bool) or int(keep_largest) != keep_largest or keep_largest < 1
    ):
        raise ValueError(f"keep_largest must be an integer >= 1, got {keep_largest}")


def _report(volume: np.ndarray, keep: np.ndarray, removed_faces: int) -> dict[str, Any]:
    """The island report from the pieces' volumes and which stay."""
    removed = volume[~keep]
    return {
        "pieces_before": len(volume),
        "pieces_after": int(keep.sum()),
        "removed_pieces": int((~keep).sum()),
        "removed_faces": int(removed_faces),
        "removed_volume_mm3": float(removed.sum()),
        "kept_volume_mm3": float(volume[keep].sum()),
        "largest_removed_mm3": float(removed.max()) if len(removed) else 0.0,
    }


def _kept_pieces(volume: np.ndarray, min_volume_mm3: float | None, keep_largest: int | None) -> np.ndarray:
    """Which pieces stay: at least ``min_volume_mm3``, then the ``keep_largest`` largest (ties: the earlier)."""
    keep = np.ones(len(volume), bool)
    if min_volume_mm3 is not None:
        keep &= volume >= min_volume_mm3
    if keep_largest is not None:
        candidates = np.flatnonzero(keep)
        by_size = candidates[np.argsort(-volume[candidates], kind="stable")]
        keep[by_size[int(keep_largest) :]] = False
    return keep


def remove_islands(
    verts: npt.NDArray[Any],
    faces: npt.NDArray[Any],
    *,
    min_volume_mm3: float | None = None,
    keep_largest: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32], dict[str, Any]]:
    """Drop the connected pieces of a mesh that enclose little volume.

    A piece's volume is the absolute value of its signed volume (vertices in (x, y, z) order); for an open piece
    that value depends on the origin but is still a usable size measure. Pieces are connected through shared
    vertices.

    Args:
        verts: (V, 3) vertices in (z, y, x) order, mm.
        faces: (F, 3) integer vertex indices.
        min_volume_mm3: drop pieces whose volume is below this (>= 0).
        keep_largest: then keep only this many pieces, the largest by volume (>= 1; ties keep the earlier piece).

    Returns:
        ``(verts, faces, info)``: the kept faces in their original order, unused vertices dropped (the rest keep
        their order), and ``info`` with ``pieces_before``, ``pieces_after``, ``removed_pieces``,
        ``removed_faces``, ``removed_volume_mm3`` (sum of the removed pieces' volumes), ``kept_volume_mm3`` and
        ``largest_removed_mm3``.

    Raises:
        ValueError: bad arrays or parameter values.
    """
    verts, faces = validate_mesh(verts, faces)
    _check_limits(min_volume_mm3, keep_largest)

    if len(faces) == 0:
        info = _report(np.zeros(0), np.zeros(0, bool), 0)
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), info

    _, vlabels = component_labels(faces, len(verts))
    flabels = vlabels[faces[:, 0]]
    # renumber to the pieces that hold faces (unused vertices are components too), in order of first face
    pieces, first, flabels = np.unique(flabels, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    flabels = rank[flabels.ravel()]
    n = len(pieces)
    volume = np.abs(np.bincount(flabels, weights=face_volumes(verts, faces), minlength=n))

    keep = _kept_pieces(volume, min_volume_mm3, keep_largest)

    face_keep = keep[flabels]
    out_v, out_f = compact_mesh(verts, faces[face_keep])
    info = _report(volume, keep, len(faces) - int(face_keep.sum()))
    return out_v, out_f, info


def measure_pieces(pos: Any, faces: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """The pieces of a device mesh: ``(label, roots, faces, volume)``, the device label of every vertex (its piece's
    root vertex), and on the host the roots in vertex order, the face count per vertex slot and each root's piece
    volume (mm^3). One sync: V ints and doubles come back, no mesh."""
    from engine.surface import kernel_specs as k
    from engine.surface.devmesh import component_labels_device
    from engine.surface.ops import backend_of

    bk = backend_of(pos)
    nv, nf = len(pos), len(faces)
    label = component_labels_device(faces, nv)
    vol = bk.zeros(nv, np.float64)
    nfaces = bk.zeros(nv, np.int32)
    runs = -(-nf // PIECE_RUN)
    bk.launch(k.PIECE_VOLUMES, runs, [pos, faces, label, nf, PIECE_RUN, vol, nfaces])
    counts = bk.to_host(nfaces)  # sync point
    roots = np.flatnonzero(counts)
    return label, roots, counts, np.abs(bk.to_host(vol)[roots])


def remove_islands_device(
    pos: Any,
    faces: Any,
    *,
    min_volume_mm3: float | None = None,
    keep_largest: int | None = None,
    consume: bool = False,
) -> tuple[Any, Any, dict[str, Any]]:
    """:func:`remove_islands` on a device mesh (packed (z, y, x) positions and faces on one ``engine.backend``):
    pieces found and measured on the device; only one volume and face count per piece come to the host to choose
    the kept ones. Pieces are ordered by their smallest vertex index (ties of ``keep_largest`` keep the earlier
    piece). Returns new device arrays and the same ``info`` as :func:`remove_islands`. ``consume``: the caller
    drops ``faces`` afterwards, so the removed pieces are marked in them rather than in a copy (a model's finishing
    within a memory budget)."""
    from engine.surface import kernel_specs as k
    from engine.surface.devmesh import compact_faces, compact_vertices
    from engine.surface.ops import backend_of, clone

    _check_limits(min_volume_mm3, keep_largest)
    bk = backend_of(pos)
    nv, nf = len(pos), len(faces)
    label, roots, counts, volume = measure_pieces(pos, faces)
    keep = _kept_pieces(volume, min_volume_mm3, keep_largest)
    info = _report(volume, keep, int(counts[roots[~keep]].sum()))
    if info["removed_pieces"] == 0:
        return pos, faces, info
    flag = np.zeros(nv, np.int32)
    flag[roots[keep]] = 1
    faces = faces if consume else clone(bk, faces)
    bk.launch(k.DROP_PIECES, nf, [faces, label, bk.from_host(flag)])
    del label
    faces = compact_faces(faces, nf - info["removed_faces"])
    pos, faces = compact_vertices(pos, faces)
    return pos, faces, info
