"""MeshLab's decimation path (the reference, and the viewing copies' last resort): slabs over processes and their
stitching."""

from __future__ import annotations

import numpy as np
import pytest

from engine.decimation import decimate_mesh
from engine.isosurface import marching_cubes_33
from tests.engine.meshutil import assert_closed_manifold, signed_volume, topology

# the reference decimation is an extra (GPL-3; the test extra has it): a machine without it skips, saying so
pytest.importorskip(
    "pymeshlab", reason="MeshLab's decimation needs the reference extra: pip install 'bonemesh[reference]'"
)


def test_parallel_slabs_stitch_into_a_closed_mesh() -> None:
    """Balls and a torus, decimated in 3 z slabs side by side: closed, same topology, same target."""
    z, y, x = np.indices((224, 288, 288), dtype=np.float32) / 3.2
    balls = np.maximum(
        20 - np.sqrt((z - 35) ** 2 + (y - 25) ** 2 + (x - 25) ** 2),
        14 - np.sqrt((z - 35) ** 2 + (y - 62) ** 2 + (x - 62) ** 2),
    )
    torus = 6 - np.sqrt((np.sqrt((y - 62) ** 2 + (x - 25) ** 2) - 16) ** 2 + (z - 35) ** 2)
    v, f = marching_cubes_33(np.maximum(balls, torus), 0.0, spacing=(0.5, 0.5, 0.5), device="cpu", closed=True)
    assert len(f) >= 300_000
    ov, of, info = decimate_mesh(v, f, reduction=0.2, method="meshlab", workers=3)
    assert info["workers"] == 3
    assert_closed_manifold(ov, of)
    before, after = topology(v, f), topology(ov, of)
    assert (after.components, after.euler) == (before.components, before.euler)
    assert before.euler < 2 * before.components  # the shapes include a handle
    assert abs(len(of) / (0.2 * len(f)) - 1) <= 0.05
    assert signed_volume(ov, of) == pytest.approx(signed_volume(v, f), rel=0.01)


def _two_slabs() -> tuple[np.ndarray, np.ndarray, list]:
    from engine.decimation.meshlab import Slab

    z, y, x = np.indices((40, 40, 40), dtype=np.float32)
    v, f = marching_cubes_33(16 - np.sqrt((z - 20) ** 2 + (y - 20) ** 2 + (x - 20) ** 2), 0.0, device="cpu")
    pts = v[:, ::-1].astype(np.float64)
    lower = pts[f].mean(axis=1)[:, 2] < 20
    slabs = []
    for mask in (lower, ~lower):
        used, inverse = np.unique(f[mask].ravel(), return_inverse=True)
        slabs.append(Slab(pts[used], inverse.reshape(-1, 3).astype(np.int32), used))
    return v, f, slabs


def test_a_slab_that_breaks_its_border_is_kept_whole() -> None:
    """If a slab came back with its cut border changed, stitching would leave a hole: that slab stays as it was."""
    from engine.decimation.meshlab import _collapse, _stitch_slabs

    v, f, slabs = _two_slabs()
    good = [_collapse(s.points, s.faces, len(s.faces) // 4) for s in slabs]
    merged, faces, kept = _stitch_slabs(good, slabs, closed=True)
    assert kept == [] and len(faces) < len(f) // 2
    assert_closed_manifold(merged[:, ::-1].astype(np.float32), faces)
    broken = [(good[0][0], good[0][1][1:]), good[1]]  # slab 0 lost a face: a hole
    merged, faces, kept = _stitch_slabs(broken, slabs, closed=True)
    assert kept == [0]
    assert_closed_manifold(merged[:, ::-1].astype(np.float32), faces)
    assert topology(merged, faces).euler == topology(v, f).euler
    moved = good[1][0].copy()
    moved[np.argmin(moved[:, 2])] += 1e-9  # slab 1 moved a border vertex (its lowest point is on the cut)
    merged, faces, kept = _stitch_slabs([good[0], (moved, good[1][1])], slabs, closed=True)
    assert kept == [1]
    assert_closed_manifold(merged[:, ::-1].astype(np.float32), faces)


def test_stitching_joins_border_vertices_only() -> None:
    """Two vertices inside one slab at the same place stay two vertices: only cut-border vertices are joined."""
    from engine.decimation.meshlab import _collapse, _stitch_slabs

    slabs = _two_slabs()[2]
    good = [_collapse(s.points, s.faces, len(s.faces) // 4) for s in slabs]
    p, q = good[0]
    top = p[np.argmin(p[:, 2])]  # the lowest point of slab 0: far from the cut at z = 20
    octa = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    octa = octa + (top - octa[4])  # a separate closed piece touching slab 0 at that point
    octa_faces = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int32
    )
    extra = (np.concatenate([p, octa]), np.concatenate([q, octa_faces + len(p)]))
    merged, faces, kept = _stitch_slabs([extra, good[1]], slabs, closed=True)
    assert kept == []
    topo = assert_closed_manifold(merged[:, ::-1].astype(np.float32), faces)
    assert topo.components == 2 and len(merged) == len(_stitch_slabs(good, slabs, closed=True)[0]) + 6
