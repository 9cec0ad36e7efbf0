"""Quadric decimation with the Warp kernels: ratio, topology, every guard on its own, determinism, real scans.

The guards are tested at the kernel level on small hand-made meshes (``price_edges`` gives each edge's cost code,
or ``NO_KEY`` when a guard refuses it), and end to end on MC33 meshes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.decimation import decimate_mesh
from engine.decimation.probe import price_edges
from engine.io.stack import load_slice_zip
from engine.isosurface import marching_cubes_33
from engine.surface.meshcheck import mesh_stats
from tests.conftest import shared_file
from tests.engine.meshutil import assert_closed_manifold, signed_volume, topology

pytestmark = pytest.mark.both_backends  # device tests run on Warp's CPU and on OpenCL (tests/conftest.py)


@pytest.fixture(scope="module")
def ball() -> tuple[np.ndarray, np.ndarray]:
    z, y, x = np.mgrid[:40, :40, :40].astype(np.float32)
    field = 16.0 - np.sqrt((z - 19.5) ** 2 + (y - 19.5) ** 2 + (x - 19.5) ** 2)
    return marching_cubes_33(field, 0.0, spacing=(0.5, 0.5, 0.5), device="cpu", closed=True)


def _zyx(points_xyz: list[tuple[float, float, float]]) -> np.ndarray:
    return np.asarray(points_xyz, np.float32)[:, ::-1].copy()


def _key(keys: dict[tuple[int, int], int], a: int, b: int) -> int:
    return keys[(min(a, b), max(a, b))]


# ------------------------------------------------------------------------------------------------ end to end
def test_ball(ball, device) -> None:
    v, f = ball
    ov, of, info = decimate_mesh(v, f, reduction=0.2, device=device)
    assert info["method"].startswith("opencl" if device.startswith("opencl") else "warp"), info["method"]
    assert abs(len(of) / (0.2 * len(f)) - 1) <= 0.02, info
    assert_closed_manifold(ov, of)
    assert info["closed_output"] and info["folds_after"] == 0
    assert signed_volume(ov, of) > 0
    assert signed_volume(ov, of) == pytest.approx(signed_volume(v, f), rel=0.01)


def test_max_triangles(ball, device) -> None:
    v, f = ball
    ov, of, info = decimate_mesh(v, f, max_triangles=2000, device=device)
    assert 2000 <= len(of) <= 2000 * 1.02, info
    assert_closed_manifold(ov, of)
    _, of2, info2 = decimate_mesh(v, f, max_triangles=10 * len(f), device=device)
    assert len(of2) == len(f) and info2["output_faces"] == len(f)


def test_deterministic(ball, device) -> None:
    v, f = ball
    a = decimate_mesh(v, f, reduction=0.3, device=device)
    b = decimate_mesh(v, f, reduction=0.3, device=device)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


@pytest.mark.parametrize("radius", [5.0, 7.0, 9.0])
def test_targets_a_few_collapses_away_are_met_exactly(radius, device) -> None:
    """The last pass keeps no more winners than collapses are left, and at least one: a hashed share of a cost bin
    can keep none (then the cheapest winner collapses) or too many (then another share is taken)."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.decimation.passes import decimate_device
    from engine.device import resolve_backend

    z, y, x = np.mgrid[:24, :24, :24].astype(np.float32)
    field = radius - np.sqrt((z - 11.3) ** 2 + (y - 11.6) ** 2 + (x - 11.5) ** 2)
    v, f = marching_cubes_33(field, 0.0, spacing=(0.5, 0.5, 0.5), device="cpu", closed=True)
    be = resolve_backend(device)
    pos, faces = be.from_host(v, VEC3F), be.from_host(f, VEC3I)
    for collapses in (1, 2, 3):
        _, out, stats = decimate_device(pos, faces, len(f) - 2 * collapses, max_passes=8)
        assert (len(out), stats.stopped) == (len(f) - 2 * collapses, "target reached"), stats.to_dict()


def test_torus_keeps_its_handle_down_to_the_guards(device) -> None:
    """Decimated as far as the guards allow, a torus stays one closed handle (link condition at work); it stops
    where no edge may collapse or, passes of none before that, stalled (the same 20 faces either way)."""
    z, y, x = np.indices((24, 40, 40), dtype=np.float32)
    torus = 4.0 - np.sqrt((np.sqrt((y - 19.5) ** 2 + (x - 19.5) ** 2) - 11) ** 2 + (z - 11.5) ** 2)
    v, f = marching_cubes_33(torus, 0.0, device="cpu", closed=True)
    ov, of, info = decimate_mesh(v, f, max_triangles=4, device=device)
    assert_closed_manifold(ov, of)
    assert (topology(ov, of).components, topology(ov, of).euler) == (1, 0)
    assert len(of) < 60 and info["stopped"].startswith(("no edge may collapse", "stalled")), info["stopped"]


def test_small_pieces_stop_at_a_tetrahedron(device) -> None:
    """Tiny closed pieces cannot fall below a tetrahedron; the report says the guards stopped the collapses."""
    z, y, x = np.indices((20, 20, 40), dtype=np.float32)
    specks = np.maximum(1.3 - np.sqrt((z - 9) ** 2 + (y - 9) ** 2 + (x - 9) ** 2),
                        1.3 - np.sqrt((z - 9) ** 2 + (y - 9) ** 2 + (x - 29) ** 2))  # fmt: skip
    v, f = marching_cubes_33(specks, 0.0, device="cpu", closed=True)
    ov, of, info = decimate_mesh(v, f, max_triangles=1, device=device)
    assert_closed_manifold(ov, of)
    assert topology(ov, of).components == 2 and len(of) == 8  # two tetrahedra
    assert info["limited_by_watertightness"]


def test_open_mesh_boundary(ball, device) -> None:
    v, f = ball
    keep = v[f].mean(axis=1)[:, 0] < 10.0  # cut off the top: an open cap
    f = f[keep]
    topo = topology(v, f)
    assert topo.boundary_edges > 0
    ov, of, info = decimate_mesh(v, f, reduction=0.3, device=device)
    assert info["boundary_preserved"] and info["folds_after"] == 0
    assert topology(ov, of).boundary_edges == topo.boundary_edges
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    border_in = {tuple(p) for p in v[np.unique(uniq[counts == 1])]}
    assert border_in <= {tuple(p) for p in ov}  # every boundary vertex kept, unmoved
    assert abs(len(of) / (0.3 * len(f)) - 1) <= 0.02, info


def test_non_manifold_input_is_left_alone(device) -> None:
    """Two balls touching at one vertex (a bow-tie vertex) decimate around it but never through it."""
    z, y, x = np.mgrid[:30, :30, :50].astype(np.float32)
    v, f = marching_cubes_33(10.0 - np.sqrt((z - 14.5) ** 2 + (y - 14.5) ** 2 + (x - 14.5) ** 2), 0.0,
                             device="cpu", closed=True)  # fmt: skip
    tip = int(np.argmax(v[:, 2]))
    v2 = v + (v[tip] - v[int(np.argmin(v[:, 2]))]) * np.array([0, 0, 1], np.float32)  # a copy touching at the tip
    bottom2 = int(np.argmin(v2[:, 2]))
    f2 = f + len(v)
    f2[f2 == bottom2 + len(v)] = tip  # share the vertex
    verts, faces = np.concatenate([v, v2]), np.concatenate([f, f2]).astype(np.int32)
    ov, of, info = decimate_mesh(verts, faces, reduction=0.3, device=device)
    assert info["vertex_classes"]["locked"] == 1
    assert tuple(verts[tip]) in {tuple(p) for p in ov}
    assert abs(len(of) / (0.3 * len(faces)) - 1) <= 0.02


def test_invalid_args(ball) -> None:
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
    with pytest.raises(ValueError, match="method"):
        decimate_mesh(v, f, reduction=0.5, method="fast")


# ------------------------------------------------------------------------------------------------ each guard
def test_guard_link_condition(device) -> None:
    """A triangular bipyramid: an equator edge has a third common neighbour (collapsing it would pinch the
    surface); an apex edge passes."""
    pts = _zyx([(1, 0, 0), (-0.5, 0.87, 0), (-0.5, -0.87, 0), (0, 0, 1.5), (0, 0, -1.5)])  # a b c N S
    faces = np.array([[3, 0, 1], [3, 1, 2], [3, 2, 0], [4, 1, 0], [4, 2, 1], [4, 0, 2]], np.int32)
    keys, no_key = price_edges(pts, faces, device=device)
    assert _key(keys, 0, 1) == no_key and _key(keys, 1, 2) == no_key
    assert _key(keys, 3, 0) != no_key


def test_guard_tetrahedron(device) -> None:
    """Every edge of a tetrahedron passes the link condition, but a collapse would leave two faces: refused."""
    pts = _zyx([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    keys, no_key = price_edges(pts, faces, device=device)
    assert len(keys) == 6 and all(k == no_key for k in keys.values())
    _, of, info = decimate_mesh(pts, faces, max_triangles=1, device=device)
    assert len(of) == 4 and info["stopped"].startswith("no edge may collapse")


def _fan(centre: tuple[float, float, float], ring: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """An open fan: vertex 0 at ``centre`` (interior), ring vertices 1.. on the border (z = 0), counter-clockwise."""
    pts = _zyx([centre, *[(x, y, 0.0) for x, y in ring]])
    n = len(ring)
    faces = np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)], np.int32)
    return pts, faces


def test_guard_flip(device) -> None:
    """Moving the centre of a non-convex fan onto a far ring vertex would flip a face: refused; a near one is fine."""
    pts, faces = _fan((0, 0, 0), [(2, 0), (0.3, 0.5), (-1, 1), (-1, -1), (0.3, -0.5)])
    keys, no_key = price_edges(pts, faces, device=device)
    assert _key(keys, 0, 1) == no_key
    assert _key(keys, 0, 2) != no_key


def test_guard_normal_turn_threshold(device) -> None:
    """A tent whose faces tilt 70 degrees: flattening it turns them 70 degrees, refused under a 60-degree limit and
    allowed under an 80-degree one (the limit is strict, not the 90 degrees of a plain flip test)."""
    ring = [(math.cos(a), math.sin(a)) for a in np.linspace(0, 2 * math.pi, 7)[:-1]]
    height = math.cos(math.pi / 6) * math.tan(math.radians(70))
    pts, faces = _fan((0, 0, height), ring)
    keys, no_key = price_edges(pts, faces, max_normal_turn_deg=60, device=device)
    assert _key(keys, 0, 1) == no_key
    keys, no_key = price_edges(pts, faces, max_normal_turn_deg=80, device=device)
    assert _key(keys, 0, 1) != no_key


def test_guard_degenerate_face(device) -> None:
    """The far ring vertex lies on the line through two others: collapsing onto it would make a zero-area face."""
    pts, faces = _fan((0, 0, 0), [(1, 0), (0.5, 1), (0, 2), (-1, 0), (0, -1)])
    keys, no_key = price_edges(pts, faces, max_normal_turn_deg=179, device=device)
    assert _key(keys, 0, 1) == no_key
    assert _key(keys, 0, 4) != no_key


def test_border_vertices_never_collapse_together(device) -> None:
    """Edges between two border vertices are never priced: the border keeps every vertex."""
    pts, faces = _fan((0, 0, 0.1), [(1, 0), (0, 1), (-1, 0), (0, -1)])
    keys, no_key = price_edges(pts, faces, device=device)
    assert all(keys[(a, b)] == no_key for a, b in keys if a > 0 and b > 0)
    assert any(keys[(0, b)] != no_key for b in range(1, 5))


# ------------------------------------------------------------------------------------------------ scans
def _check_scan(vol: np.ndarray, level: float, spacing: tuple[float, float, float], reduction: float) -> None:
    v, f = marching_cubes_33(vol, level, spacing=spacing, device="cpu", closed=True)
    ov, of, info = decimate_mesh(v, f, reduction=reduction, device="cpu")
    s = mesh_stats(ov, of)
    assert s["watertight"] and s["manifold"] and s["vertex_manifold"], s
    assert topology(ov, of).components == topology(v, f).components  # the link condition keeps the topology
    assert topology(ov, of).euler == topology(v, f).euler
    assert abs(info["volume_change"]) < 0.01
    assert info["folds_after"] <= info["folds_before"]  # no flipped faces: no new folds
    assert not info["limited_by_watertightness"]
    assert abs(len(of) / (reduction * len(f)) - 1) <= 0.02


def test_headsq_bundled() -> None:
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

    _check_scan(load_slice_zip(HEADSQ_ZIP), 1150.5, HEADSQ_SPACING_ZYX_MM, 0.2)


def test_cranium() -> None:
    vol = load_slice_zip(shared_file("cranium_ct", "cranium_ct_png16.zip"))
    _check_scan(vol, 1324.5, (1.5, 0.9570312, 0.9570312), 0.5)


def test_a_decimation_the_guards_stall_stops_before_its_pass_limit(ball, device) -> None:
    """A piece pinned on many planes (as a group of slabs is on its borders) cannot reach a far target: once its last
    ``STALL_PASSES`` passes remove under ``STALL_SHARE`` of the faces still to go it stops ("stalled"), not after
    ``MAX_PASSES`` passes of a few collapses each; what it gives is still closed and keeps every pinned vertex."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.backend.select import get_backend
    from engine.decimation.passes import MAX_PASSES, STALL_PASSES, STALL_SHARE, decimate_carrying

    v, f = ball
    be = get_backend(device)
    pinned = (np.floor(v[:, 0] / 0.5).astype(int) % 3 == 0).astype(np.int32)  # every third plane of the grid
    res = decimate_carrying(be.from_host(v, VEC3F), be.from_host(f, VEC3I), len(f) // 50, locked=be.from_host(pinned))
    st = res.stats
    assert st.stopped.startswith("stalled"), st.to_dict()
    assert STALL_PASSES <= st.passes < MAX_PASSES
    assert 2 * sum(st.collapses[-STALL_PASSES:]) < STALL_SHARE * (len(res.faces) - len(f) // 50)
    ov, of = be.to_host(res.pos).reshape(-1, 3), be.to_host(res.faces).reshape(-1, 3)
    assert_closed_manifold(ov, of)
    kept = be.to_host(res.kept)
    assert np.isin(np.flatnonzero(pinned), kept).all()
