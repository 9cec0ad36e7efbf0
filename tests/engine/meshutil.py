"""Mesh checks shared by the engine tests: validity, topology (components, Euler), manifoldness."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class Topology:
    components: int
    euler: int
    boundary_edges: int  # edges in one face
    nonmanifold_edges: int  # edges in three or more faces
    inconsistent_edges: int  # interior edges whose two faces run them the same way
    duplicate_faces: int


def assert_valid_mesh(verts: np.ndarray, faces: np.ndarray) -> None:
    """Indices in range, no repeated vertex in a face, finite coordinates, every vertex used."""
    assert verts.dtype == np.float32 and verts.ndim == 2 and verts.shape[1] == 3
    assert faces.dtype == np.int32 and faces.ndim == 2 and faces.shape[1] == 3
    assert np.isfinite(verts).all()
    if len(faces) == 0:
        assert len(verts) == 0
        return
    assert faces.min() >= 0 and faces.max() < len(verts)
    assert (faces[:, 0] != faces[:, 1]).all() and (faces[:, 1] != faces[:, 2]).all()
    assert (faces[:, 0] != faces[:, 2]).all()
    assert np.bincount(faces.ravel(), minlength=len(verts)).min() > 0, "unused vertices"


def topology(verts: np.ndarray, faces: np.ndarray) -> Topology:
    nv = len(verts)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    undirected = np.sort(directed, axis=1)
    keys = undirected[:, 0] * nv + undirected[:, 1]
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    # consistent winding: an edge in two faces appears once in each direction
    forward = (directed[:, 0] < directed[:, 1]).astype(np.int64)
    fwd_count = np.bincount(inverse, weights=forward, minlength=len(uniq))
    two = counts == 2
    inconsistent = int(np.count_nonzero(two & (fwd_count != 1)))
    ev = np.stack([uniq // max(nv, 1), uniq % max(nv, 1)], axis=1)
    graph = sp.coo_matrix((np.ones(len(ev)), (ev[:, 0], ev[:, 1])), shape=(nv, nv))
    ncomp = connected_components(graph, directed=False)[0] if nv else 0
    dup = len(faces) - len(np.unique(np.sort(faces, axis=1), axis=0)) if len(faces) else 0
    return Topology(
        components=int(ncomp),
        euler=int(nv - len(uniq) + len(faces)),
        boundary_edges=int(np.count_nonzero(counts == 1)),
        nonmanifold_edges=int(np.count_nonzero(counts > 2)),
        inconsistent_edges=inconsistent,
        duplicate_faces=int(dup),
    )


def assert_closed_manifold(verts: np.ndarray, faces: np.ndarray) -> Topology:
    """Watertight and 2-manifold: every edge in exactly two faces, consistent winding, no duplicate faces."""
    assert_valid_mesh(verts, faces)
    topo = topology(verts, faces)
    assert topo.boundary_edges == 0, topo
    assert topo.nonmanifold_edges == 0, topo
    assert topo.inconsistent_edges == 0, topo
    assert topo.duplicate_faces == 0, topo
    return topo


def signed_volume(verts_zyx: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume with vertices taken in (x, y, z) order (positive for outward normals)."""
    v = verts_zyx[:, ::-1].astype(np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def refine_trilinear(volume: np.ndarray, k: int) -> np.ndarray:
    """Insert k-1 samples between neighbours along each axis by trilinear interpolation (exact, float64)."""
    out = volume.astype(np.float64)
    for axis in range(3):
        n = out.shape[axis]
        x = np.arange((n - 1) * k + 1) / k
        i0 = np.minimum(np.floor(x).astype(np.int64), n - 2)
        w = (x - i0).reshape([-1 if a == axis else 1 for a in range(3)])
        out = np.take(out, i0, axis=axis) * (1 - w) + np.take(out, i0 + 1, axis=axis) * w
    return out
