"""Fast numpy diagnostics of a triangle mesh, for the pipeline report and for the stages that must keep a mesh valid.

Conventions: vertices (V, 3) in (z, y, x) order in mm, faces (F, 3) integer indices; normals are outward when the
vertices are taken in (x, y, z) order, so a closed mesh with outward normals has a positive signed volume.

Everything is vectorised and works in chunks where a temporary would scale with the face count: one ``np.sort``
of the 3F half-edge keys gives watertightness, edge-manifoldness and winding; the vertex-manifold test (one fan
of faces around every vertex) costs one ``np.argsort`` of the same keys and runs only where the edges are fine.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

_CHUNK = 1 << 22  # faces per chunk for the float64 volume / area sums


def _check_inputs(verts: npt.NDArray[Any], faces: npt.NDArray[Any]) -> tuple[np.ndarray, np.ndarray]:
    verts = np.asarray(verts)
    faces = np.asarray(faces)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"Expected vertices of shape (V, 3), got {verts.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"Expected faces of shape (F, 3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"Expected integer faces, got dtype {faces.dtype}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise ValueError(f"Face indices must lie in [0, {len(verts) - 1}], got [{faces.min()}, {faces.max()}]")
    return verts, faces


def component_labels(faces: npt.NDArray[Any], n_vertices: int) -> tuple[int, npt.NDArray[np.int32]]:
    """Connected components of the mesh's vertex graph (vertices sharing a face are connected).

    Args:
        faces: (F, 3) integer vertex indices.
        n_vertices: number of vertices; unused vertices form components of their own.

    Returns:
        ``(n_components, labels)`` with ``labels`` (n_vertices,) int32 in ``[0, n_components)``.
    """
    faces = np.asarray(faces)
    if n_vertices == 0:
        return 0, np.zeros(0, np.int32)
    # two edges per face connect its three vertices
    rows = np.concatenate([faces[:, 0], faces[:, 1]]).astype(np.int32, copy=False)
    cols = np.concatenate([faces[:, 1], faces[:, 2]]).astype(np.int32, copy=False)
    graph = sp.csr_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    n, labels = connected_components(graph, directed=True, connection="weak")
    return int(n), labels.astype(np.int32, copy=False)


def face_volumes(verts: npt.NDArray[Any], faces: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    """Per-face signed volume contributions ``a . (b x c) / 6`` with vertices in (x, y, z) order (float64)."""
    out = np.empty(len(faces), np.float64)
    for lo in range(0, len(faces), _CHUNK):
        f = faces[lo : lo + _CHUNK]
        a, b, c = (verts[f[:, k]][:, ::-1].astype(np.float64) for k in range(3))
        out[lo : lo + len(f)] = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return out


def face_normals(verts: npt.NDArray[Any], faces: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    """Unnormalised face normals ``(b - a) x (c - a)`` in (x, y, z) order (float64, length = twice the area)."""
    v = np.asarray(verts)[:, ::-1].astype(np.float64)
    a = v[faces[:, 0]]
    return np.cross(v[faces[:, 1]] - a, v[faces[:, 2]] - a)


def _volume_area(verts: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """Signed volume and area in one chunked float64 pass."""
    vol = area = 0.0
    for lo in range(0, len(faces), _CHUNK):
        f = faces[lo : lo + _CHUNK]
        a, b, c = (verts[f[:, k]][:, ::-1].astype(np.float64) for k in range(3))
        vol += float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
        n = np.cross(b - a, c - a)
        area += float(np.sqrt(np.einsum("ij,ij->i", n, n)).sum()) / 2.0
    return vol, area


def _halfedge_keys(faces: np.ndarray, n_vertices: int) -> npt.NDArray[np.int64]:
    """Key ``(min * V + max) * 2 + (a > b)`` of every half-edge a->b, in order (face 0 edges 01 12 20, face 1...)."""
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    key = np.minimum(a, b).astype(np.int64)
    key *= n_vertices
    key += np.maximum(a, b)
    key *= 2
    key += a > b
    return key


def edge_report(faces: npt.NDArray[Any], n_vertices: int) -> dict[str, int]:
    """Edge counts: ``edges`` (distinct undirected), ``boundary_edges`` (in one face), ``nonmanifold_edges`` (in
    three or more), ``inconsistent_edges`` (in two faces that run it the same way), ``duplicate_halfedges``."""
    faces = np.asarray(faces)
    if len(faces) == 0:
        return {"edges": 0, "boundary_edges": 0, "nonmanifold_edges": 0, "inconsistent_edges": 0}
    keys = np.sort(_halfedge_keys(faces, n_vertices))
    und = keys >> 1
    starts = np.flatnonzero(np.concatenate([[True], und[1:] != und[:-1]]))
    counts = np.diff(np.append(starts, len(und)))
    two = starts[counts == 2]
    # sorted: a consistent pair is (key with direction bit 0, key with direction bit 1)
    inconsistent = int(np.count_nonzero((keys[two] & 1) == (keys[two + 1] & 1)))
    return {
        "edges": len(starts),
        "boundary_edges": int(np.count_nonzero(counts == 1)),
        "nonmanifold_edges": int(np.count_nonzero(counts > 2)),
        "inconsistent_edges": inconsistent,
    }


def fan_counts(faces: npt.NDArray[Any], n_vertices: int) -> npt.NDArray[np.int64]:
    """Number of face fans around each vertex of a closed, edge-manifold, consistently wound mesh.

    A used vertex is manifold exactly when it has one fan (0 for unused vertices). Each corner (face f, vertex v)
    is followed around v by the corner of v in the face across the edge that enters v in f; the fans are the
    cycles of that permutation, counted by pointer doubling.

    Raises:
        ValueError: the mesh has a boundary or non-manifold edge (the fans are not cycles).
    """
    faces = np.asarray(faces)
    nh = 3 * len(faces)
    if nh == 0:
        return np.zeros(n_vertices, np.int64)
    keys = _halfedge_keys(faces, n_vertices)
    order = np.argsort(keys)
    und = keys[order] >> 1
    if nh % 2 or np.any(und[0::2] != und[1::2]) or (nh > 2 and np.any(und[2::2] == und[1:-1:2])):
        raise ValueError("fan_counts needs a closed edge-manifold mesh (every edge in exactly two faces)")
    itype = np.int32 if nh < 2**31 else np.int64
    twin = np.empty(nh, itype)
    twin[order[0::2]] = order[1::2]
    twin[order[1::2]] = order[0::2]
    del order, und, keys
    h = np.arange(nh, dtype=itype)
    prev = h - 1 + 3 * (h % 3 == 0)  # half-edge entering the corner's vertex in the same face
    nxt = twin[prev]  # starts at the same vertex, in the next face around it
    del twin, prev
    label = h
    while True:  # label = min index over the cycle; cycles are short (vertex valence)
        new = np.minimum(label, label[nxt])
        nxt = nxt[nxt]
        if np.array_equal(new, label):
            break
        label = new
    return np.bincount(faces.reshape(-1)[label == h], minlength=n_vertices)


def vertex_fans(faces: npt.NDArray[Any], n_vertices: int) -> int:
    """Total number of face fans (see :func:`fan_counts`); equals the used vertex count for a manifold mesh."""
    return int(fan_counts(faces, n_vertices).sum())


def mesh_stats(verts: npt.NDArray[Any], faces: npt.NDArray[Any], *, vertex_manifold: bool = True) -> dict[str, Any]:
    """Diagnostics of a triangle mesh.

    Args:
        verts: (V, 3) vertices in (z, y, x) order, mm.
        faces: (F, 3) integer vertex indices.
        vertex_manifold: also test that every vertex has a single fan of faces (one argsort of 3F keys; only done
            when the edges are closed and manifold, otherwise the mesh is already reported non-manifold).

    Returns:
        A dict with ``n_vertices``, ``n_faces``, ``n_edges``, ``watertight`` (every edge in exactly two faces),
        ``manifold`` (no edge in more than two faces, consistent winding, no repeated vertex in a face, and where
        tested a single fan at every vertex), ``vertex_manifold`` (bool or None when not tested),
        ``boundary_edges``, ``nonmanifold_edges``, ``inconsistent_edges``, ``degenerate_faces``, ``components``,
        ``euler`` (V - E + F over all vertices), ``volume_mm3`` (signed, positive for outward normals),
        ``area_mm2`` and ``bbox_mm`` (``{"min": [x, y, z], "max": [x, y, z]}`` or None for an empty mesh).
    """
    verts, faces = _check_inputs(verts, faces)
    nv, nf = len(verts), len(faces)
    degenerate = int(
        np.count_nonzero((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2]))
    )
    edges = edge_report(faces, nv)
    edge_ok = edges["nonmanifold_edges"] == 0 and edges["inconsistent_edges"] == 0 and degenerate == 0
    watertight = nf > 0 and edges["boundary_edges"] == 0 and edges["nonmanifold_edges"] == 0
    vman: bool | None = None
    if vertex_manifold and edge_ok and watertight:
        used = int(np.count_nonzero(np.bincount(faces.ravel(), minlength=nv)))
        vman = vertex_fans(faces, nv) == used
    ncomp, _ = component_labels(faces, nv)
    volume, area = _volume_area(verts, faces) if nf else (0.0, 0.0)
    if nv:
        xyz = verts[:, ::-1]
        bbox: dict[str, list[float]] | None = {
            "min": [float(x) for x in xyz.min(axis=0)],
            "max": [float(x) for x in xyz.max(axis=0)],
        }
    else:
        bbox = None
    return {
        "n_vertices": nv,
        "n_faces": nf,
        "n_edges": edges["edges"],
        "watertight": bool(watertight),
        "manifold": bool(edge_ok and vman is not False),
        "vertex_manifold": vman,
        "boundary_edges": edges["boundary_edges"],
        "nonmanifold_edges": edges["nonmanifold_edges"],
        "inconsistent_edges": edges["inconsistent_edges"],
        "degenerate_faces": degenerate,
        "components": ncomp,
        "euler": int(nv - edges["edges"] + nf),
        "volume_mm3": volume,
        "area_mm2": area,
        "bbox_mm": bbox,
    }


def is_closed_manifold(verts: npt.NDArray[Any], faces: npt.NDArray[Any]) -> bool:
    """Watertight, edge- and vertex-manifold, consistently wound, without degenerate faces."""
    _, faces = _check_inputs(verts, faces)
    nv = len(verts)
    if len(faces) == 0:
        return False
    if np.any((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])):
        return False
    e = edge_report(faces, nv)
    if e["boundary_edges"] or e["nonmanifold_edges"] or e["inconsistent_edges"]:
        return False
    used = int(np.count_nonzero(np.bincount(faces.ravel(), minlength=nv)))
    return vertex_fans(faces, nv) == used


def validate_mesh(verts: npt.NDArray[Any], faces: npt.NDArray[Any]) -> tuple[npt.NDArray[Any], npt.NDArray[Any]]:
    """Check (V, 3) vertices and (F, 3) integer faces with indices in range; return them as arrays.

    Raises:
        ValueError: what was expected and what arrived.
    """
    verts = np.asarray(verts)
    faces = np.asarray(faces)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"Expected vertices of shape (V, 3), got {verts.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"Expected integer faces of shape (F, 3), got {faces.dtype} {faces.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise ValueError(f"Face indices must lie in [0, {len(verts) - 1}], got [{faces.min()}, {faces.max()}]")
    return verts, faces


FOLDS_MAX_FACES = 10_000_000  # above this, ``folds`` is not counted (the edge sort would cost more than a decimation)


def signed_volume(pts_xyz: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (pts_xyz[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def folds(pts_xyz: np.ndarray, faces: np.ndarray) -> int | None:
    """Edges whose two faces' normals are more than 90 degrees apart (a flipped face makes such folds); None above
    ``FOLDS_MAX_FACES`` faces, where the edge sort would cost more than the decimation."""
    if len(faces) == 0:
        return 0
    if len(faces) > FOLDS_MAX_FACES:
        return None
    n = np.cross(pts_xyz[faces[:, 1]] - pts_xyz[faces[:, 0]], pts_xyz[faces[:, 2]] - pts_xyz[faces[:, 0]])
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    fid = np.tile(np.arange(len(faces)), 3)
    key = np.minimum(e[:, 0], e[:, 1]) * (int(faces.max()) + 1) + np.maximum(e[:, 0], e[:, 1])
    order = np.argsort(key, kind="stable")
    k = key[order]
    same = k[1:] == k[:-1]
    a, b = fid[order][:-1][same], fid[order][1:][same]
    return int(np.count_nonzero(np.einsum("ij,ij->i", n[a], n[b]) < 0))


def boundary_kept(pts: np.ndarray, faces: np.ndarray, out_pts: np.ndarray) -> bool:
    from engine.surface.smooth import unique_edges

    edges, on_border = unique_edges(faces)
    border = pts[np.unique(edges[on_border])]
    if len(border) == 0:
        return True
    kept = {tuple(p) for p in out_pts}
    return all(tuple(p) in kept for p in border)
