"""The surface stages (``engine.surface``: stars and vertex classes, compaction, mesh statistics, components and
island removal, surface-preserving smoothing, normals) and the output layout (``engine.job.outputs.lay_out``) on OpenCL
(``engine.backend``, PoCL in CI) give what Warp's CPU path gives, on the same real mesh (MC33 of the bundled headsq
at its bone level): the same topology (faces, stars, classes, components, Euler characteristic) and positions,
normals and file buffers equal to float tolerance (bit for bit on PoCL). The Warp CPU run is the reference."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from engine.backend.base import VEC3F, VEC3I
from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.params import SmoothParams
from tests.engine.conftest import backend_for

TOL_MM = 1e-5  # positions (mm) and unit normals: float32 tolerance for a device that rounds differently


@functools.cache
def _headsq_mesh() -> tuple[np.ndarray, np.ndarray]:
    """MC33 of the bundled headsq at its bone level, closed: ~40k vertices, ~80k faces, 75 pieces."""
    from engine.io.stack import load_slice_zip
    from engine.isosurface import marching_cubes_33

    data = load_slice_zip(HEADSQ_ZIP)
    return marching_cubes_33(data, HEADSQ_LEVEL, spacing=HEADSQ_SPACING_ZYX_MM, device="cpu", closed=True)


@pytest.fixture
def backends(opencl):
    """(Warp's CPU backend, the OpenCL backend): the OpenCL one skips, with the reason, where none can run."""
    return backend_for("warp-cpu"), opencl


def _upload(bk, verts: np.ndarray | None = None, faces: np.ndarray | None = None):
    v, f = _headsq_mesh()
    verts = v if verts is None else verts
    faces = f if faces is None else faces
    return bk.from_host(verts, VEC3F), bk.from_host(faces, VEC3I)


def _each(backends, run):
    """``run(backend)`` on Warp's CPU path and on OpenCL."""
    return [run(bk) for bk in backends]


def _close(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape and a.dtype == b.dtype
    diff = float(np.abs(a.astype(np.float64) - b).max()) if a.size else 0.0
    assert diff <= TOL_MM, f"max difference {diff:g}"


def test_stars_and_vertex_classes_are_the_same(backends):
    """The stars and classes are equal on both backends, and each counts its classes on the device as the host
    counts the classes it reads back."""
    from engine.surface.devmesh import Incidence, class_counts, vertex_classes

    def run(bk):
        verts, faces_np = _headsq_mesh()
        faces_np = faces_np.copy()
        faces_np[::101] = -1  # some removed faces, as in a decimation: open borders
        pos, faces = _upload(bk, np.vstack([verts, np.zeros((2, 3), np.float32)]), faces_np)  # two unused vertices
        inc = Incidence(len(pos)).build(faces, len(faces))
        state = vertex_classes(faces, inc)
        return [bk.to_host(a) for a in (*inc.inputs, state)], class_counts(state)

    (warp, warp_counts), (cl, cl_counts) = _each(backends, run)
    for a, b in zip(warp, cl, strict=True):
        np.testing.assert_array_equal(a[: int(warp[1].sum())], b[: int(warp[1].sum())])  # the stars' filled slots
    host_counts = np.bincount(warp[3], minlength=4)
    np.testing.assert_array_equal(warp_counts, host_counts)
    np.testing.assert_array_equal(cl_counts, host_counts)
    assert host_counts[0] > 0.5 * len(warp[3]) and host_counts[1] > 0 and host_counts[3] == 2  # free, border, unused


def test_mesh_statistics_are_the_same(backends):
    """Watertight, manifold, components, Euler characteristic, edges: equal; volume and area: the same sums (runs
    in order on the device, then on the host)."""
    from engine.surface import mesh_stats
    from engine.surface.devmesh import mesh_stats_device

    warp, cl = _each(backends, lambda bk: mesh_stats_device(*_upload(bk)))
    assert warp == cl
    host = mesh_stats(*_headsq_mesh())
    assert (cl["watertight"], cl["components"], cl["euler"]) == (host["watertight"], host["components"], host["euler"])
    assert cl["volume_mm3"] == pytest.approx(host["volume_mm3"], rel=1e-9)


def test_components_are_the_same(backends):
    from engine.surface import component_labels
    from engine.surface.devmesh import component_labels_device

    def run(bk):
        pos, faces = _upload(bk)
        return bk.to_host(component_labels_device(faces, len(pos)))

    warp, cl = _each(backends, run)
    np.testing.assert_array_equal(warp, cl)
    n, _ = component_labels(_headsq_mesh()[1], len(_headsq_mesh()[0]))
    assert len(np.unique(cl)) == n > 1


@pytest.mark.parametrize("limits", [{"min_volume_mm3": 50.0}, {"keep_largest": 3}])
def test_island_removal_is_the_same(backends, limits):
    """The same pieces kept, the same compacted mesh in the same order; the pieces' volumes (float64 atomic sums,
    in any order on a parallel device) to 1e-12."""
    from engine.surface.islands import remove_islands_device

    def run(bk):
        pos, faces, info = remove_islands_device(*_upload(bk), **limits)
        return bk.to_host(pos), bk.to_host(faces), info

    (wpos, wfaces, winfo), (cpos, cfaces, cinfo) = _each(backends, run)
    np.testing.assert_array_equal(wfaces, cfaces)
    np.testing.assert_array_equal(wpos, cpos)  # copied, not computed
    assert winfo["removed_pieces"] > 0
    for key, value in winfo.items():
        assert cinfo[key] == (value if isinstance(value, int) else pytest.approx(value, rel=1e-12)), key


def test_compaction_and_bounds_are_the_same(backends):
    """The first 3000 faces and every 7th removed, then the unused vertices: the same arrays, in order; the same
    bounding box."""
    from engine.surface.devmesh import bounds, compact_faces, compact_vertices

    verts, faces = _headsq_mesh()
    marked = faces.copy()
    marked[::7] = -1
    marked[:3000] = -1
    alive = int((marked[:, 0] >= 0).sum())

    def run(bk):
        pos, f = _upload(bk, faces=marked)
        pos, f = compact_vertices(pos, compact_faces(f, alive))
        return bk.to_host(pos), bk.to_host(f), bounds(pos)

    (wpos, wf, wbox), (cpos, cf, cbox) = _each(backends, run)
    np.testing.assert_array_equal(wf, cf)
    np.testing.assert_array_equal(wpos, cpos)
    np.testing.assert_array_equal(np.asarray(wbox), np.asarray(cbox))
    assert len(cf) == alive and len(cpos) < len(verts)


def test_smoothing_and_normals_are_the_same_and_deterministic(backends):
    """Three iterations of surface-preserving Laplacian smoothing, then normals: the same moves per iteration,
    positions and normals within float tolerance (the max difference is reported on failure); OpenCL twice gives
    the same bits."""
    from engine.surface.normals import normals_device
    from engine.surface.smooth import smooth_device

    params = SmoothParams(iterations=3, angle_deg=2.0)

    def run(bk):
        pos, faces = _upload(bk)
        pos, info = smooth_device(pos, faces, params)
        return bk.to_host(pos), bk.to_host(normals_device(pos, faces)), info

    (wpos, wn, winfo), (cpos, cn, cinfo) = _each(backends, run)
    assert winfo == cinfo and min(winfo["moved_per_iteration"]) > 100
    _close(wpos, cpos)
    _close(wn, cn)
    again = run(backends[1])
    np.testing.assert_array_equal(again[0], cpos)
    np.testing.assert_array_equal(again[1], cn)


def test_host_wrappers_take_an_opencl_device(backends):
    """``smooth_mesh`` and ``vertex_normals`` on ``"opencl"`` give Warp CPU's result."""
    from engine.surface import smooth_mesh, vertex_normals

    verts, faces = _headsq_mesh()
    params = SmoothParams(iterations=1)
    wpos, winfo = smooth_mesh(verts, faces, params, "cpu")
    cpos, cinfo = smooth_mesh(verts, faces, params, backends[1])
    assert winfo == cinfo
    _close(wpos, cpos)
    _close(vertex_normals(verts, faces, "cpu"), vertex_normals(verts, faces, backends[1]))


def test_meshes_move_between_backends(backends):
    from engine.surface.devmesh import on_device

    warp, cl = backends
    pos, faces = _upload(cl)
    back = on_device(warp.device, pos, faces)
    there = on_device(cl, *back)
    for a, b in zip((pos, faces), there, strict=True):
        np.testing.assert_array_equal(cl.to_host(a), cl.to_host(b))
    assert on_device(cl, pos)[0] is pos


def _mirroring_frame():
    """A patient frame that rotates 30 degrees, mirrors x and shifts: every layout kernel's branch runs."""
    from engine.orient import Frame

    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    frame = Frame(rotation @ np.diag([-1.0, 1.0, 1.0]), np.array([-12.5, 40.0, 3.25]), "test")
    assert frame.mirrored
    return frame


def test_layout_is_the_same(backends):
    """The patient frame, the STL facets (in chunks), the glTF buffers and bounds, the zero-area count."""
    from engine.job.outputs import lay_out
    from engine.surface.normals import normals_device

    frame = _mirroring_frame()

    def run(bk):
        pos, faces = _upload(bk)
        return lay_out(pos, faces, normals_device(pos, faces), frame, chunk_faces=30_000)

    warp, cl = _each(backends, run)
    np.testing.assert_array_equal(warp.tris, cl.tris)
    np.testing.assert_array_equal(warp.tris[:, ::-1], _headsq_mesh()[1])  # mirrored: the winding reversed
    for name in ("facets", "gltf_pos", "gltf_normals", "centre_xyz"):
        _close(getattr(warp, name), getattr(cl, name))
    for side in ("min", "max"):
        np.testing.assert_allclose(warp.gltf_bounds[side], cl.gltf_bounds[side], rtol=0, atol=TOL_MM)
    assert warp.zero_area == cl.zero_area
    for name in ("pos", "view_pos", "view_normals"):  # the device arrays the viewing copies start from
        _close(backends[0].to_host(getattr(warp, name)), backends[1].to_host(getattr(cl, name)))
