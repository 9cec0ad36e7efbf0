"""The quadric decimation on OpenCL (``engine.backend``, PoCL in CI) gives what Warp's CPU path gives: on a real
mesh (MC33 of the bundled headsq at its bone level) decimated to reduction 0.2 and 0.5, the same faces and the same
vertices, bit for bit (the OpenCL C kernels do Warp's arithmetic in Warp's order, and every decision is independent
of the order work items run in); and hence the same topology (watertight, 2-manifold, components, Euler
characteristic), face count and no new folds. Every guard is checked on both backends at the kernel level; the
viewing copies (with clustering and the piece census) and the budgeted paths (tiled rounds on the device and from
the host, pinned vertices, seams across slab groups' borders) give the same meshes too. The Warp CPU run is the
reference; the OpenCL runs skip, saying why, only where PyOpenCL or every OpenCL platform is missing."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.decimation import decimate_mesh
from engine.decimation.probe import price_edges
from engine.surface.meshcheck import mesh_stats
from tests.engine.meshutil import topology


@functools.cache
def _headsq_mesh() -> tuple[np.ndarray, np.ndarray]:
    """MC33 of the bundled headsq at its bone level, closed: ~40k vertices, ~80k faces, dozens of pieces."""
    from engine.io.stack import load_slice_zip
    from engine.isosurface import marching_cubes_33

    data = load_slice_zip(HEADSQ_ZIP)
    return marching_cubes_33(data, HEADSQ_LEVEL, spacing=HEADSQ_SPACING_ZYX_MM, device="cpu", closed=True)


@functools.cache
def _decimated(reduction: float, backend_name: str) -> tuple[np.ndarray, np.ndarray, dict]:
    from tests.engine.conftest import backend_for

    v, f = _headsq_mesh()
    return decimate_mesh(v, f, reduction=reduction, device=backend_for(backend_name))


@pytest.mark.parametrize("reduction", [0.2, 0.5])
def test_headsq_same_as_warp_cpu(reduction: float, opencl) -> None:
    v, f = _headsq_mesh()
    wv, wf, winfo = _decimated(reduction, "warp-cpu")
    ov, of, oinfo = _decimated(reduction, "opencl")
    assert oinfo["method"].startswith("opencl") and winfo["method"].startswith("warp")
    # the ideal: the same faces, the same vertices
    np.testing.assert_array_equal(of, wf)
    np.testing.assert_array_equal(ov, wv)
    assert (
        (oinfo["passes"], oinfo["stopped"])
        == (winfo["passes"], winfo["stopped"])
        == (winfo["passes"], "target reached")
    )
    # and what follows from it, checked on its own: topology, face count, no flipped faces
    s = mesh_stats(ov, of)
    assert s["watertight"] and s["manifold"] and s["vertex_manifold"], s
    t_in, t_out = topology(v, f), topology(ov, of)
    assert (
        (t_out.components, t_out.euler)
        == (t_in.components, t_in.euler)
        == (topology(wv, wf).components, topology(wv, wf).euler)
    )
    assert len(of) == len(wf) and abs(len(of) / (reduction * len(f)) - 1) <= 0.02
    assert oinfo["folds_after"] == winfo["folds_after"] <= oinfo["folds_before"]
    assert oinfo["vertex_classes"] == winfo["vertex_classes"]


def test_deterministic_on_opencl(opencl) -> None:
    v, f = _headsq_mesh()
    a = decimate_mesh(v, f, reduction=0.5, device=opencl)
    ov, of, _ = _decimated(0.5, "opencl")
    np.testing.assert_array_equal(a[1], of)
    np.testing.assert_array_equal(a[0], ov)


# ------------------------------------------------------------------------------------------------ each guard
def _zyx(points_xyz: list[tuple[float, float, float]]) -> np.ndarray:
    return np.asarray(points_xyz, np.float32)[:, ::-1].copy()


def _key(keys: dict[tuple[int, int], int], a: int, b: int) -> int:
    return keys[(min(a, b), max(a, b))]


def _fan(centre: tuple[float, float, float], ring: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """An open fan: vertex 0 at ``centre`` (interior), ring vertices 1.. on the border (z = 0), counter-clockwise."""
    pts = _zyx([centre, *[(x, y, 0.0) for x, y in ring]])
    n = len(ring)
    return pts, np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)], np.int32)


def _priced(backend, pts: np.ndarray, faces: np.ndarray, **kw) -> tuple[dict[tuple[int, int], int], int]:
    """The codes on ``backend``, checked equal to Warp's CPU codes (the same guards, the same costs)."""
    from tests.engine.conftest import backend_for

    keys, no_key = price_edges(pts, faces, device=backend, **kw)
    assert (keys, no_key) == price_edges(pts, faces, device=backend_for("warp-cpu"), **kw)
    return keys, no_key


def test_guard_link_condition(backend) -> None:
    """A triangular bipyramid: an equator edge has a third common neighbour (refused); an apex edge passes."""
    pts = _zyx([(1, 0, 0), (-0.5, 0.87, 0), (-0.5, -0.87, 0), (0, 0, 1.5), (0, 0, -1.5)])
    faces = np.array([[3, 0, 1], [3, 1, 2], [3, 2, 0], [4, 1, 0], [4, 2, 1], [4, 0, 2]], np.int32)
    keys, no_key = _priced(backend, pts, faces)
    assert _key(keys, 0, 1) == no_key and _key(keys, 1, 2) == no_key
    assert _key(keys, 3, 0) != no_key


def test_guard_tetrahedron(backend) -> None:
    """Every edge of a tetrahedron passes the link condition, but a collapse would leave two faces: refused."""
    pts = _zyx([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    keys, no_key = _priced(backend, pts, faces)
    assert len(keys) == 6 and all(k == no_key for k in keys.values())
    _, of, info = decimate_mesh(pts, faces, max_triangles=1, device=backend)
    assert len(of) == 4 and info["stopped"].startswith("no edge may collapse")


def test_guard_flip(backend) -> None:
    """Moving the centre of a non-convex fan onto a far ring vertex would flip a face: refused; a near one is fine."""
    pts, faces = _fan((0, 0, 0), [(2, 0), (0.3, 0.5), (-1, 1), (-1, -1), (0.3, -0.5)])
    keys, no_key = _priced(backend, pts, faces)
    assert _key(keys, 0, 1) == no_key and _key(keys, 0, 2) != no_key


def test_guard_normal_turn_threshold(backend) -> None:
    """A tent whose faces tilt 70 degrees: flattening it is refused under a 60-degree limit, allowed under 80."""
    ring = [(math.cos(a), math.sin(a)) for a in np.linspace(0, 2 * math.pi, 7)[:-1]]
    pts, faces = _fan((0, 0, math.cos(math.pi / 6) * math.tan(math.radians(70))), ring)
    keys, no_key = _priced(backend, pts, faces, max_normal_turn_deg=60)
    assert _key(keys, 0, 1) == no_key
    keys, no_key = _priced(backend, pts, faces, max_normal_turn_deg=80)
    assert _key(keys, 0, 1) != no_key


def test_guard_degenerate_face(backend) -> None:
    """The far ring vertex lies on the line through two others: collapsing onto it would make a zero-area face."""
    pts, faces = _fan((0, 0, 0), [(1, 0), (0.5, 1), (0, 2), (-1, 0), (0, -1)])
    keys, no_key = _priced(backend, pts, faces, max_normal_turn_deg=179)
    assert _key(keys, 0, 1) == no_key and _key(keys, 0, 4) != no_key


def test_guard_border(backend) -> None:
    """Edges between two border vertices are never priced (the border keeps every vertex, unmoved); an open cap
    decimates with its border intact, the same faces as on Warp's CPU path."""
    from tests.engine.conftest import backend_for

    pts, faces = _fan((0, 0, 0.1), [(1, 0), (0, 1), (-1, 0), (0, -1)])
    keys, no_key = _priced(backend, pts, faces)
    assert all(keys[(a, b)] == no_key for a, b in keys if a > 0 and b > 0)
    assert any(keys[(0, b)] != no_key for b in range(1, 5))
    v, f = _headsq_mesh()
    cap = f[v[f].mean(axis=1)[:, 0] < 40.0]  # the slices below 40 mm: an open mesh
    ov, of, info = decimate_mesh(v, cap, reduction=0.3, device=backend)
    assert info["boundary_preserved"] and info["folds_after"] <= info["folds_before"]
    assert topology(ov, of).boundary_edges == topology(v, cap).boundary_edges
    wv, wf, _ = decimate_mesh(v, cap, reduction=0.3, device=backend_for("warp-cpu"))
    np.testing.assert_array_equal(of, wf)
    np.testing.assert_array_equal(ov, wv)


def test_non_manifold_vertex_is_left_alone(backend) -> None:
    """Two tetrahedron-like fans sharing one vertex (a bow tie): it is LOCKED on both backends and kept."""
    pts = _zyx([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (-1, 0, 0), (0, -1, 0), (0, 0, -1)])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [0, 5, 4], [0, 4, 6], [0, 6, 5], [4, 5, 6]],
                     np.int32)  # fmt: skip
    _, of, info = decimate_mesh(pts, faces, max_triangles=1, device=backend)
    assert info["vertex_classes"]["locked"] == 1 and len(of) == 8


# ------------------------------------------------------------------------------------------------ viewing copies
def _on(backend_name: str, v: np.ndarray, f: np.ndarray):
    from engine.backend.base import VEC3F, VEC3I
    from tests.engine.conftest import backend_for

    be = backend_for(backend_name)
    return be, be.from_host(v, VEC3F), be.from_host(f, VEC3I)


def _without_seconds(summary: dict) -> dict:
    """A summary without its wall times (which differ between runs)."""
    return {
        k: (_without_seconds(x) if isinstance(x, dict) else x)
        for k, x in summary.items()
        if k not in ("seconds", "timings")
    }


def test_clustering_and_census_same_as_warp_cpu(opencl) -> None:
    """Quadric vertex clustering (the viewing copies' last resort) and the piece census: the same on both."""
    from engine.decimation.cluster import cluster_device, piece_census

    v, f = _headsq_mesh()
    got = {}
    for name in ("warp-cpu", "opencl"):
        be, pos, faces = _on(name, v, f)
        p, q, info = cluster_device(pos, faces, 5000)
        census = piece_census(pos, faces)
        got[name] = (be.to_host(p), be.to_host(q), _without_seconds(info), census)
    (wp_, wf, winfo, wc), (op, of, oinfo, oc) = got["warp-cpu"], got["opencl"]
    assert 0.95 * 5000 <= len(of) <= 5000 and oinfo == winfo
    np.testing.assert_array_equal(of, wf)
    np.testing.assert_array_equal(op, wp_)
    assert len(oc) == len(wc) == topology(v, f).components
    for field in ("faces", "vertices"):
        np.testing.assert_array_equal(getattr(oc, field), getattr(wc, field))
    # float64 sums of face volumes, added atomically: in another order on a GPU (NVIDIA's OpenCL: 1e-13 apart)
    np.testing.assert_allclose(oc.volume, wc.volume, rtol=1e-9)


def test_viewing_copies_same_as_warp_cpu(opencl) -> None:
    """The phone copy (guarded decimation) and a tiny AR copy (pieces dropped, then clustered): the same copies and
    the same summaries on both backends."""
    from engine.decimation import viewing_copies

    v, f = _headsq_mesh()
    got = {}
    for name in ("warp-cpu", "opencl"):
        be, pos, faces = _on(name, v, f)
        copies = viewing_copies(pos, faces, [20000, 300], pieces=topology(v, f).components, closed=True)
        got[name] = [(be.to_host(p), be.to_host(q), _without_seconds(s)) for p, q, s in copies]
    for (wp_, wf, ws), (op, of, os_) in zip(got["warp-cpu"], got["opencl"], strict=True):
        assert os_ == ws and len(of) == os_["faces"]
        np.testing.assert_array_equal(of, wf)
        np.testing.assert_array_equal(op, wp_)
    phone, ar = got["opencl"]
    assert phone[2]["topology_preserved"] and mesh_stats(phone[0], phone[1])["watertight"]
    assert len(ar[1]) <= 300 and not ar[2]["over_budget"]


# ------------------------------------------------------------------------------------------------ within a budget
@pytest.mark.parametrize("rounds", ["device", "host"])
def test_tiled_rounds_same_as_warp_cpu(rounds: str, opencl) -> None:
    """A mesh decimated in tiles with pinned borders (a budget far under its decimation), in rounds on the device
    or on the host: the same mesh on both backends, its topology kept."""
    from engine.budget import Budget
    from engine.decimation import decimate_within

    v, f = _headsq_mesh()
    target = len(f) // 5
    budget = Budget(len(f) * 300 // 4, max_tiles=1 if rounds == "host" else Budget.max_tiles)
    got = {}
    for name in ("warp-cpu", "opencl"):
        be, pos, faces = _on(name, v, f)
        p, q, info = decimate_within(pos, faces, target, budget, be)
        got[name] = (be.to_host(p), be.to_host(q), info)
    (wv, wf, winfo), (ov, of, oinfo) = got["warp-cpu"], got["opencl"]
    assert oinfo["tiled"] and oinfo.get("on", "host") == rounds and len(oinfo["rounds"][0]["tiles"]) >= 2
    np.testing.assert_array_equal(of, wf)
    np.testing.assert_array_equal(ov, wv)
    assert _without_seconds(oinfo["rounds"][0]) == _without_seconds(winfo["rounds"][0])
    t_in, t_out = topology(v, f), topology(ov, of)
    assert (t_out.components, t_out.euler, t_out.boundary_edges) == (t_in.components, t_in.euler, 0)
    assert target <= len(of) <= target * 1.02


def test_pinned_vertices_stay_put_on_opencl(opencl) -> None:
    """``decimate_carrying`` with pinned vertices and quadrics carried out: none moved or removed, and the same
    result (positions, faces, kept ids, quadrics) as Warp's CPU path."""
    from engine.decimation.passes import decimate_carrying

    v, f = _headsq_mesh()
    lock = (v[:, 0] < np.quantile(v[:, 0], 0.3)).astype(np.int32)  # the lowest 30 % of the vertices
    got = {}
    for name in ("warp-cpu", "opencl"):
        be, pos, faces = _on(name, v, f)
        res = decimate_carrying(pos, faces, len(f) // 4, locked=be.from_host(lock))
        got[name] = [be.to_host(a) for a in (res.pos, res.faces, res.kept, res.quad)]
    for w, o in zip(got["warp-cpu"], got["opencl"], strict=True):
        np.testing.assert_array_equal(o.reshape(w.shape), w)
    out, _, kept, _ = got["opencl"]
    assert set(np.flatnonzero(lock)) <= set(kept)  # none removed
    pinned = lock[kept] != 0
    np.testing.assert_array_equal(out[pinned], v[kept[pinned]])  # none moved


@pytest.mark.parametrize("where", ["device", "host"])
def test_seams_across_group_borders_same_as_warp_cpu(where: str, opencl) -> None:
    """The finish of a decimation begun in groups of slabs (``finish_groups``): the faces near the groups' borders
    decimated again with the rest pinned, on the device beside the mesh or from the host (then tiled rounds): the
    same mesh on both backends, its topology kept."""
    from engine.budget import Budget
    from engine.decimation import finish_groups
    from engine.decimation.tiles import HostMesh

    v, f = _headsq_mesh()
    borders = [float(z) for z in np.quantile(v[:, 0], [0.3, 0.6])]
    target = int(len(f) * 0.9)
    budget = Budget(len(f) * 300, last_pass=False, seams_beside=False)
    origin = 0.5 * (v.min(axis=0).astype(np.float64) + v.max(axis=0))
    got = {}
    for name in ("warp-cpu", "opencl"):
        be, pos, faces = _on(name, v, f)
        host = HostMesh(v, f, np.zeros((0, 10)), origin) if where == "host" else None
        pieces = None if where == "host" else [pos, faces, None]
        p, q, info = finish_groups(host, pieces, origin, target, budget, borders, 6.0, device=be)
        got[name] = (be.to_host(p), be.to_host(q), info)
    (wv, wf, winfo), (ov, of, oinfo) = got["warp-cpu"], got["opencl"]
    assert ("seams" in oinfo) and _without_seconds(oinfo["seams"]) == _without_seconds(winfo["seams"])
    np.testing.assert_array_equal(of, wf)
    np.testing.assert_array_equal(ov, wv)
    t_in, t_out = topology(v, f), topology(ov, of)
    assert (t_out.components, t_out.euler, t_out.boundary_edges) == (t_in.components, t_in.euler, 0)
    assert target <= len(of) < len(f)
