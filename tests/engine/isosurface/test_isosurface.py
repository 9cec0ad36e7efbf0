"""marching_cubes_33: input validation, conventions (axes, spacing, orientation), closing, slabs, devices."""

from __future__ import annotations

import numpy as np
import pytest

from engine.isosurface import IsosurfaceStats, marching_cubes_33
from tests.engine.meshutil import assert_closed_manifold, assert_valid_mesh, signed_volume, topology


def ball(shape: tuple[int, int, int] = (24, 26, 28), centre=(11.3, 12.6, 13.1), radius: float = 8.2) -> np.ndarray:
    z, y, x = np.indices(shape, dtype=np.float32)
    r = np.sqrt((z - centre[0]) ** 2 + (y - centre[1]) ** 2 + (x - centre[2]) ** 2)
    return (radius - r).astype(np.float32)  # positive inside: a bright ball


def mesh_key(verts: np.ndarray, faces: np.ndarray, decimals: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Order-invariant form of a mesh: sorted vertex rows, and faces as sorted triples of vertex rows."""
    v = np.round(verts.astype(np.float64), decimals)
    order = np.lexsort(v.T[::-1])
    rank = np.empty(len(v), np.int64)
    rank[order] = np.arange(len(v))
    f = np.sort(rank[faces], axis=1)
    f = f[np.lexsort(f.T[::-1])]
    return v[order], f


# ------------------------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("volume", "match"),
    [
        (np.zeros((4, 4), np.float32), "3-D volume"),
        (np.zeros((4, 4, 4, 4), np.float32), "3-D volume"),
        (np.zeros((1, 4, 4), np.float32), "at least 2"),
        (np.zeros((4, 4, 4), np.float64), "dtype"),
        (np.zeros((4, 4, 4), np.int32), "dtype"),
        ([[[0.0]]], "numpy array"),
    ],
)
def test_rejects_bad_volume(volume, match):
    with pytest.raises(ValueError, match=match):
        marching_cubes_33(volume, 0.5, device="cpu")


@pytest.mark.parametrize("spacing", [(1.0, 0.0, 1.0), (1.0, -2.0, 1.0), (1.0, 1.0), (1.0, float("nan"), 1.0), "abc"])
def test_rejects_bad_spacing(spacing):
    with pytest.raises(ValueError, match="spacing"):
        marching_cubes_33(ball(), 0.0, spacing=spacing, device="cpu")


def test_rejects_nan(device):
    vol = ball()
    vol[3, 4, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        marching_cubes_33(vol, 0.0, device=device)


@pytest.mark.parametrize("level", [float("nan"), float("inf"), "x"])
def test_rejects_bad_level(level):
    with pytest.raises(ValueError, match="level"):
        marching_cubes_33(ball(), level, device="cpu")


def test_rejects_bad_device():
    with pytest.raises(ValueError, match="device"):
        marching_cubes_33(ball(), 0.0, device="gpu7")


@pytest.mark.parametrize("closed", [False, True])
@pytest.mark.parametrize("level", [-100.0, 100.0])
def test_level_outside_data_range_is_empty(device, closed, level):
    verts, faces = marching_cubes_33(ball(), level, device=device, closed=closed)
    assert verts.shape == (0, 3) and faces.shape == (0, 3)
    assert verts.dtype == np.float32 and faces.dtype == np.int32


# ------------------------------------------------------------------------------------------- conventions
def test_bright_ball_is_closed_positive_and_accurate(device):
    radius = 8.2
    verts, faces = marching_cubes_33(ball(radius=radius), 0.0, device=device)
    topo = assert_closed_manifold(verts, faces)
    assert topo.components == 1 and topo.euler == 2
    vol = signed_volume(verts, faces)
    assert vol > 0, "normals must point from above the level toward below it"
    np.testing.assert_allclose(vol, 4 / 3 * np.pi * radius**3, rtol=0.01)


def test_axes_and_spacing_follow_skimage(device):
    skimage = pytest.importorskip("skimage.measure")
    vol = ball()
    spacing = (1.5, 0.7, 0.3)
    verts, faces = marching_cubes_33(vol, 0.0, spacing=spacing, device=device)
    ref_v, ref_f, _, _ = skimage.marching_cubes(vol, 0.0, spacing=spacing, method="lewiner")
    assert len(verts) == len(ref_v)  # a smooth ball has no ambiguous cells: same vertex set
    a, _ = mesh_key(verts, faces)
    b, _ = mesh_key(ref_v.astype(np.float32), ref_f.astype(np.int32))
    np.testing.assert_allclose(a, b, atol=1e-4)
    # and the same orientation convention
    assert np.sign(signed_volume(verts, faces)) == np.sign(signed_volume(ref_v, ref_f))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.float32])
def test_integer_dtypes_match_float(device, dtype):
    vol = np.clip((ball() * 10 + 100).round(), 0, 250)
    level = 100.5
    ref = marching_cubes_33(vol.astype(np.float32), level, device=device)
    got = marching_cubes_33(vol.astype(dtype), level, device=device)
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-6)


def test_dark_ball_inside_bright_box_open_vs_closed(device):
    vol = -ball()  # bright everywhere except a dark ball
    verts, faces = marching_cubes_33(vol, 0.0, device=device)
    assert_closed_manifold(verts, faces)
    assert signed_volume(verts, faces) < 0  # normals point into the dark ball
    verts, faces = marching_cubes_33(vol, 0.0, device=device, closed=True)
    topo = assert_closed_manifold(verts, faces)
    assert topo.components == 2 and topo.euler == 4  # the box skin and the cavity
    assert signed_volume(verts, faces) > 0


def test_open_surface_at_the_border_and_closing(device):
    _, _, x = np.indices((10, 12, 14), dtype=np.float32)
    vol = 5.5 - x  # a slab x < 5.5 above the level, touching the array's faces
    verts, faces = marching_cubes_33(vol, 0.0, device=device)
    assert_valid_mesh(verts, faces)
    topo = topology(verts, faces)
    assert topo.boundary_edges > 0 and topo.nonmanifold_edges == 0
    np.testing.assert_allclose(verts[:, 2], 5.5, atol=1e-5)
    verts, faces = marching_cubes_33(vol, 0.0, device=device, closed=True)
    topo = assert_closed_manifold(verts, faces)
    assert topo.components == 1 and topo.euler == 2
    # the closing caps sit half a voxel outside the array
    np.testing.assert_allclose(verts.min(axis=0), [-0.5, -0.5, -0.5], atol=1e-6)
    np.testing.assert_allclose(verts.max(axis=0), [9.5, 11.5, 5.5], atol=1e-5)


def test_vertices_are_shared(device):
    verts, faces = marching_cubes_33(ball(), 0.0, device=device)
    rounded = np.round(verts, 5)
    assert len(np.unique(rounded, axis=0)) == len(verts)  # one vertex per crossing, not a triangle soup
    assert np.bincount(faces.ravel()).min() >= 3  # each is shared by the faces around it


# ------------------------------------------------------------------------------------------- slabs
@pytest.mark.parametrize("closed", [False, True])
def test_slabs_give_the_identical_mesh(device, closed):
    rng = np.random.default_rng(7)
    vol = rng.integers(0, 100, size=(45, 20, 22)).astype(np.uint8)
    one = IsosurfaceStats()
    v1, f1 = marching_cubes_33(vol, 49.5, device=device, closed=closed, stats=one)
    many = IsosurfaceStats()
    v2, f2 = marching_cubes_33(vol, 49.5, device=device, closed=closed, max_device_bytes=1, stats=many)
    assert one.slabs == 1 and many.slabs == 6  # one block layer (8 cell layers) per slab
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(f1, f2)
    assert one.table_misses == 0 and many.table_misses == 0


def test_budget_bounds_the_slab_working_set(device):
    vol = (ball((64, 40, 40), centre=(31.5, 19.5, 19.5), radius=18.0) * 10).astype(np.int16)
    budget = 3_000_000
    stats = IsosurfaceStats()
    _, f = marching_cubes_33(vol, 0.5, device=device, max_device_bytes=budget, stats=stats)
    assert stats.slabs > 1
    assert stats.peak_slab_bytes <= budget
    ref = marching_cubes_33(vol, 0.5, device=device)
    np.testing.assert_array_equal(f, ref[1])


def test_empty_blocks_are_skipped(device):
    vol = np.zeros((64, 64, 64), np.uint8)
    vol[30:34, 30:34, 30:34] = 200
    stats = IsosurfaceStats()
    verts, faces = marching_cubes_33(vol, 100.0, device=device, stats=stats)
    assert_closed_manifold(verts, faces)
    assert stats.active_blocks <= 8 < stats.blocks


# ------------------------------------------------------------------------------------------- devices
@pytest.mark.gpu
@pytest.mark.parametrize("closed", [False, True])
def test_cuda_matches_cpu(closed):
    rng = np.random.default_rng(3)
    vol = rng.normal(size=(40, 33, 35)).astype(np.float32)
    cpu = marching_cubes_33(vol, 0.1, device="cpu", closed=closed)
    gpu = marching_cubes_33(vol, 0.1, device="cuda", closed=closed)
    np.testing.assert_array_equal(gpu[1], cpu[1])  # same topology, same faces
    np.testing.assert_allclose(gpu[0], cpu[0], rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------- device-resident
@pytest.mark.parametrize("budget", [None, 1])
def test_device_resident_matches_numpy(device, budget):
    import warp as wp

    from engine.isosurface import extract_isosurface

    rng = np.random.default_rng(9)
    vol = rng.integers(0, 200, size=(30, 17, 19)).astype(np.uint16)
    ref_v, ref_f = marching_cubes_33(vol, 99.5, spacing=(2.0, 1.0, 0.5), device=device, closed=True)
    field = wp.array(vol, device=device)
    stats = IsosurfaceStats(profile=True)
    v, f = extract_isosurface(field, 99.5, spacing=(2.0, 1.0, 0.5), closed=True, max_device_bytes=budget, stats=stats)
    assert str(v.device) == str(field.device)
    np.testing.assert_array_equal(v.numpy(), ref_v)
    np.testing.assert_array_equal(f.numpy(), ref_f)
    assert {"classify blocks", "count", "scan", "emit"} <= set(stats.timings)


def test_device_resident_rejects_bad_field(device):
    import warp as wp

    from engine.isosurface import extract_isosurface

    with pytest.raises(ValueError, match="3-D Warp array"):
        extract_isosurface(wp.zeros((4, 4), dtype=wp.float32, device=device), 0.0)
    with pytest.raises(ValueError, match="3-D Warp array"):
        extract_isosurface(np.zeros((4, 4, 4), np.float32), 0.0)
