"""Quadric decimation: ratio, watertightness, orientation, boundary, real scan."""

from __future__ import annotations

import numpy as np
import pytest

from engine.io.stack import load_slice_zip
from engine.isosurface import marching_cubes_33
from engine.stages.decimate import decimate_mesh
from engine.stages.meshcheck import mesh_stats
from tests.conftest import shared_file
from tests.engine.meshutil import assert_closed_manifold, signed_volume, topology


@pytest.fixture(scope="module")
def ball() -> tuple[np.ndarray, np.ndarray]:
    z, y, x = np.mgrid[:40, :40, :40].astype(np.float32)
    field = 16.0 - np.sqrt((z - 19.5) ** 2 + (y - 19.5) ** 2 + (x - 19.5) ** 2)
    return marching_cubes_33(field, 0.0, spacing=(0.5, 0.5, 0.5), device="cpu", closed=True)


def test_ball(ball: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = ball
    ov, of, info = decimate_mesh(v, f, reduction=0.2)
    assert abs(len(of) / (0.2 * len(f)) - 1) <= 0.05, info
    assert_closed_manifold(ov, of)
    assert info["closed_output"] and info["folds_after"] == 0
    assert signed_volume(ov, of) > 0
    assert signed_volume(ov, of) == pytest.approx(signed_volume(v, f), rel=0.01)


def test_max_triangles(ball: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = ball
    ov, of, info = decimate_mesh(v, f, max_triangles=2000)
    assert abs(len(of) / 2000 - 1) <= 0.05, info
    assert_closed_manifold(ov, of)
    _, of2, info2 = decimate_mesh(v, f, max_triangles=10 * len(f))
    assert len(of2) == len(f) and info2["output_faces"] == len(f)


def test_open_mesh_boundary(ball: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = ball
    keep = v[f].mean(axis=1)[:, 0] < 10.0  # cut off the top: an open cap
    f = f[keep]
    topo = topology(v, f)
    assert topo.boundary_edges > 0
    ov, of, info = decimate_mesh(v, f, reduction=0.3)
    assert info["boundary_preserved"] and info["folds_after"] == 0
    assert topology(ov, of).boundary_edges == topo.boundary_edges
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    border_in = {tuple(p) for p in v[np.unique(uniq[counts == 1])]}
    assert border_in <= {tuple(p) for p in ov}  # every boundary vertex kept, unmoved
    assert abs(len(of) / (0.3 * len(f)) - 1) <= 0.05, info


def _check_scan(vol: np.ndarray, level: float, spacing: tuple[float, float, float], reduction: float) -> None:
    v, f = marching_cubes_33(vol, level, spacing=spacing, device="cpu", closed=True)
    ov, of, info = decimate_mesh(v, f, reduction=reduction)
    s = mesh_stats(ov, of)
    assert s["watertight"] and s["manifold"] and s["vertex_manifold"], s
    assert topology(ov, of).components == topology(v, f).components  # the link condition keeps the topology
    assert topology(ov, of).euler == topology(v, f).euler
    assert abs(info["volume_change"]) < 0.01
    assert info["folds_after"] <= info["folds_before"]  # no flipped faces: no new folds
    assert not info["limited_by_watertightness"]
    assert abs(len(of) / (reduction * len(f)) - 1) <= 0.05


def test_headsq_bundled() -> None:
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

    _check_scan(load_slice_zip(HEADSQ_ZIP), 1150.5, HEADSQ_SPACING_ZYX_MM, 0.2)


def test_cranium() -> None:
    vol = load_slice_zip(shared_file("cranium_ct", "cranium_ct_png16.zip"))
    _check_scan(vol, 1324.5, (1.5, 0.9570312, 0.9570312), 0.2)


def test_invalid_args(ball: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = ball
    with pytest.raises(ValueError, match="exactly one"):
        decimate_mesh(v, f)
    with pytest.raises(ValueError, match="exactly one"):
        decimate_mesh(v, f, reduction=0.5, max_triangles=10)
    for bad in (0.0, 1.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match="reduction"):
            decimate_mesh(v, f, reduction=bad)
    with pytest.raises(ValueError, match="max_triangles"):
        decimate_mesh(v, f, max_triangles=0)
    with pytest.raises(ValueError, match="empty"):
        decimate_mesh(v, np.zeros((0, 3), np.int32), reduction=0.5)


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
    ov, of, info = decimate_mesh(v, f, reduction=0.2, workers=3)
    assert info["workers"] == 3
    assert_closed_manifold(ov, of)
    before, after = topology(v, f), topology(ov, of)
    assert (after.components, after.euler) == (before.components, before.euler)
    assert before.euler < 2 * before.components  # the shapes include a handle
    assert abs(len(of) / (0.2 * len(f)) - 1) <= 0.05
    assert signed_volume(ov, of) == pytest.approx(signed_volume(v, f), rel=0.01)


def _two_slabs() -> tuple[np.ndarray, np.ndarray, list]:
    from engine.stages.decimate import Slab

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
    from engine.stages.decimate import _collapse, _stitch_slabs

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
    from engine.stages.decimate import _collapse, _stitch_slabs

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
