"""The symmetry plane on a device (issue 42): the nearest surface voxels of the mirror-ICP looked up in a
closest-feature transform on the backend (``engine.defect.ops.closest_feature`` / ``nearest_feature``, Warp kernels
and OpenCL C twins) instead of the host's k-d tree. Warp's CPU path and OpenCL give the same plane, bit for bit, and
the tree's plane to a small fraction of a degree and of a voxel; a plane on OpenCL runs no Warp kernel."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.params import OrientParams

ORIENT = OrientParams(first_slice="superior")


@functools.cache
def _headsq_cut() -> Any:
    """headsq (93 x 64 x 64) with a 30 mm trephination at the left temple."""
    from engine.defect.synthetic import cut_defect
    from engine.io import load_volume

    headsq = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    return cut_defect(headsq, HEADSQ_LEVEL, (1.0, -0.1, 0.0), 30.0, slices=(4, 18), orient=ORIENT)


def _features(shape: tuple[int, int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) < 0.02
    mask[shape[0] // 2, 1, 2] = True
    return np.flatnonzero(mask).astype(np.int32)


def test_the_closest_feature_transform_is_exact_and_the_same_on_every_backend(backend) -> None:
    from scipy import ndimage as ndi

    from engine.defect.ops import closest_feature

    shape, sp = (9, 13, 11), (1.5, 0.7, 0.9)
    flat = _features(shape, 3)
    rank = backend.to_host(closest_feature(backend, backend.from_host(flat), shape, sp))
    assert rank.min() >= 0 and np.array_equal(rank[flat], np.arange(len(flat)))  # a feature is its own
    mask = np.zeros(int(np.prod(shape)), dtype=bool)
    mask[flat] = True
    exact = ndi.distance_transform_edt(~mask.reshape(shape), sampling=sp).reshape(-1)
    at = np.stack(np.unravel_index(np.arange(mask.size), shape), axis=1) * sp
    got = np.linalg.norm(at - at[flat[rank]], axis=1)  # the distance to the feature it names: the nearest one's
    np.testing.assert_allclose(got, exact, rtol=1e-5, atol=1e-5)
    none = closest_feature(backend, backend.from_host(np.zeros(0, np.int32)), shape, sp)
    assert np.all(backend.to_host(none) == -1)
    if backend.kind == "opencl":
        from engine.backend import get_backend

        cpu = get_backend("cpu")
        ref = cpu.to_host(closest_feature(cpu, cpu.from_host(flat), shape, sp))
        assert np.array_equal(ref, rank)  # bit for bit


def test_the_nearest_feature_of_a_point_is_the_k_d_trees(backend) -> None:
    from scipy.spatial import cKDTree

    from engine.defect.kernel_specs import BOX
    from engine.defect.ops import closest_feature, nearest_feature

    shape, sp = (10, 14, 12), (2.0, 0.6, 0.8)
    flat = _features(shape, 5)
    feats = np.stack(np.unravel_index(flat, shape), axis=1)[:, ::-1] * sp[::-1]  # x, y, z mm
    rng = np.random.default_rng(11)
    extent = np.asarray(shape[::-1]) * sp[::-1]
    points = rng.uniform(-0.2 * extent, 1.2 * extent, size=(500, 3))  # some outside the grid
    d_flat = backend.from_host(flat)
    rank = closest_feature(backend, d_flat, shape, sp)
    box = backend.struct(BOX, nz=shape[0], ny=shape[1], nx=shape[2], lz=0, ly=0, lx=0, sz=sp[0], sy=sp[1], sx=sp[2])
    out = backend.empty(len(points), np.int32)
    d_points = backend.from_host(points.astype(np.float32).reshape(-1))
    nearest_feature(backend, d_points, len(points), rank, d_flat, box, out, max_scan=1 << 20)
    got = backend.to_host(out)
    want, _ = cKDTree(feats).query(points)
    dist = np.linalg.norm(points - feats[got], axis=1)
    np.testing.assert_allclose(dist, want, rtol=1e-5, atol=1e-4)
    # with no room to look around, the nearest of the 8 voxels' closest features: never nearer than the nearest
    nearest_feature(backend, d_points, len(points), rank, d_flat, box, out, max_scan=0)
    near8 = np.linalg.norm(points - feats[backend.to_host(out)], axis=1)
    assert np.all(near8 >= want - 1e-4) and np.mean(near8 <= want + 1e-4) > 0.5


def test_the_nearest_feature_is_the_same_however_many_threads_share_a_points_look(backend) -> None:
    """The query's look around a point split over threads (every ``parts``-th row of its box each, then joined) gives
    the one thread's answer, ties to the lower rank included: points on a 1 mm grid's half-voxel lattice lie at
    exactly the same distance from several features, so the lower rank must win across the parts."""
    from engine.defect.kernel_specs import BOX
    from engine.defect.ops import closest_feature, nearest_feature

    shape, sp = (9, 11, 10), (1.0, 1.0, 1.0)
    flat = np.flatnonzero(np.random.default_rng(7).random(shape) < 0.15).astype(np.int32)
    feats = np.stack(np.unravel_index(flat, shape), axis=1)[:, ::-1].astype(np.float64)  # x, y, z mm
    rng = np.random.default_rng(5)
    half = rng.integers(-2, 2 * np.asarray(shape[::-1]) + 2, size=(400, 3)) * 0.5  # exact in float32
    points = np.concatenate([half, rng.uniform(-2.0, np.asarray(shape[::-1]) + 2.0, size=(200, 3))])
    d_flat = backend.from_host(flat)
    rank = closest_feature(backend, d_flat, shape, sp)
    box = backend.struct(BOX, nz=shape[0], ny=shape[1], nx=shape[2], lz=0, ly=0, lx=0, sz=sp[0], sy=sp[1], sx=sp[2])
    d_points = backend.from_host(points.astype(np.float32).reshape(-1))
    got = {}
    for parts in (1, 3, 32):
        out = backend.empty(len(points), np.int32)
        nearest_feature(backend, d_points, len(points), rank, d_flat, box, out, max_scan=1 << 20, parts=parts)
        got[parts] = backend.to_host(out)
    assert np.array_equal(got[1], got[3]) and np.array_equal(got[1], got[32])
    # on the lattice the distances are exact: the nearest feature with the lowest rank among the equally near
    d2 = ((half[:, None, :] - feats[None, :, :]) ** 2).sum(axis=2)
    want = np.argmin(d2, axis=1)  # the first (lowest rank) of the smallest
    ties = (d2 == d2.min(axis=1, keepdims=True)).sum(axis=1) > 1
    assert ties.sum() > 100  # the lattice holds many ties
    assert np.array_equal(got[32][: len(half)], want)


def test_the_skulls_voxels_surface_and_normals_on_the_device_are_the_hosts(backend) -> None:
    from engine.defect.grid import surface_voxels
    from engine.defect.ops import set_voxels, sobel, upload_mask
    from engine.defect.plane import _unit_normals, surface_normals

    rng = np.random.default_rng(2)
    shape, sp = (7, 9, 8), np.array([0.8, 0.6, 1.5])  # x, y, z mm
    mask = rng.random(shape) < 0.6
    mask[:, 0, :] = True  # set voxels on the grid's border
    d_mask = upload_mask(backend, mask)
    assert np.array_equal(set_voxels(backend, d_mask, shape), np.flatnonzero(mask))
    surf = surface_voxels(mask)
    flat = set_voxels(backend, d_mask, shape, surface=True)
    assert np.array_equal(np.stack(np.unravel_index(flat, shape), axis=1), surf)
    at = np.ravel_multi_index(tuple(surf.T), shape).astype(np.int32)
    grad = sobel(backend, d_mask, shape, backend.from_host(at), len(at))
    assert np.array_equal(_unit_normals(grad, sp), surface_normals(mask, surf, sp))


def _angle_deg(a: Any, b: Any) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(a, b)))))))


def test_the_plane_on_warp_cpu_and_opencl_is_the_same_and_the_trees(opencl) -> None:
    from engine.defect import find_symmetry_plane

    vol = _headsq_cut().volume
    host = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT)
    cpu = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device="cpu", where="device")
    ocl = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device=opencl, where="device")
    assert cpu.normal_grid == ocl.normal_grid and cpu.offset_grid_mm == ocl.offset_grid_mm
    assert (cpu.residual_mm, cpu.inlier_fraction, cpu.iterations) == (ocl.residual_mm, ocl.inlier_fraction,
                                                                       ocl.iterations)  # fmt: skip
    voxel = min(HEADSQ_SPACING_ZYX_MM)
    assert _angle_deg(cpu.normal_grid, host.normal_grid) < 0.1
    assert abs(cpu.offset_grid_mm - host.offset_grid_mm) < 0.1 * voxel
    assert abs(cpu.residual_mm - host.residual_mm) < 0.01 and abs(cpu.inlier_fraction - host.inlier_fraction) < 0.01


def test_the_plane_with_a_point_hint_is_the_same_on_the_device(backend) -> None:
    from engine.defect import DefectParams, find_symmetry_plane
    from engine.defect.grid import Grid

    cut = _headsq_cut()
    vol = cut.volume
    grid = Grid.of(vol, ORIENT)
    centre = grid.to_patient(grid.xyz(np.argwhere(cut.removed).mean(axis=0)))  # the cut's middle
    hint = DefectParams(point_lps_mm=tuple(float(v) for v in centre))
    host = find_symmetry_plane(vol, HEADSQ_LEVEL, hint, orient=ORIENT)
    dev = find_symmetry_plane(vol, HEADSQ_LEVEL, hint, orient=ORIENT, device=backend, where="device")
    assert _angle_deg(dev.normal_grid, host.normal_grid) < 0.1
    assert abs(dev.offset_grid_mm - host.offset_grid_mm) < 0.1 * min(HEADSQ_SPACING_ZYX_MM)


def test_a_plane_on_opencl_launches_no_warp_kernel(opencl, monkeypatch) -> None:
    import pyopencl as cl
    import warp as wp
    import warp._src.context as wp_context

    from engine.defect import find_symmetry_plane

    vol = _headsq_cut().volume
    find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device=opencl, where="device")  # the programs built first
    enqueued = []
    real = cl.enqueue_nd_range_kernel

    def no_warp(kernel: Any, *a: Any, **k: Any) -> Any:
        raise AssertionError(f"a Warp kernel was launched: {getattr(kernel, 'key', kernel)}")

    def spy(*a: Any, **k: Any) -> Any:
        enqueued.append(1)
        return real(*a, **k)

    monkeypatch.setattr(wp, "launch", no_warp)
    monkeypatch.setattr(wp_context, "launch", no_warp)
    monkeypatch.setattr(cl, "enqueue_nd_range_kernel", spy)
    plane = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device=opencl, where="device")
    assert plane.inlier_fraction > 0.5 and len(enqueued) > plane.iterations


def test_a_box_over_the_working_set_falls_back_to_the_tree(monkeypatch) -> None:
    from engine.backend import get_backend
    from engine.defect import find_symmetry_plane

    vol = _headsq_cut().volume
    cpu = get_backend("cpu")
    monkeypatch.setattr(type(cpu), "default_budget", lambda self: 0)
    host = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT)
    fallback = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device=cpu, where="device")
    assert fallback.normal_grid == host.normal_grid and fallback.offset_grid_mm == host.offset_grid_mm


def test_the_largest_piece_on_the_device_is_scipys(backend) -> None:
    from scipy import ndimage as ndi

    from engine.defect.grid import CONNECTIVITY
    from engine.defect.ops import largest_piece, upload_mask

    rng = np.random.default_rng(4)
    shape = (12, 15, 14)
    bone = ndi.binary_opening(rng.random(shape) < 0.45)  # many pieces, touching by edges and corners
    labels, n = ndi.label(bone, structure=CONNECTIVITY)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    mask, pieces = largest_piece(backend, upload_mask(backend, bone), shape)
    assert pieces == n > 2
    assert np.array_equal(backend.to_host(mask).reshape(shape).astype(bool), labels == int(sizes.argmax()))
    # two pieces of four voxels: the one whose first voxel comes first in the flat order, as scipy numbers them
    twins = np.zeros((4, 5, 6), dtype=bool)
    twins[3, 4, 0:4] = True  # a row at the end
    twins[1, 0, 3] = twins[0, 1, 2] = twins[1, 1, 1] = twins[0, 2, 0] = True  # a chain by corners, from (0, 1, 2)
    mask, pieces = largest_piece(backend, upload_mask(backend, twins), twins.shape)
    assert pieces == 2
    want = np.zeros_like(twins)
    want[1, 0, 3] = want[0, 1, 2] = want[1, 1, 1] = want[0, 2, 0] = True
    assert np.array_equal(backend.to_host(mask).reshape(twins.shape).astype(bool), want)


def test_the_masks_on_the_device_are_the_hosts(backend) -> None:
    from engine.defect.grid import bone_and_skull
    from engine.defect.ops import bone_and_skull as bone_and_skull_on
    from engine.errors import EmptySurfaceError

    data = _headsq_cut().volume.data
    host = bone_and_skull(data, HEADSQ_LEVEL)
    dev = bone_and_skull_on(backend, data, HEADSQ_LEVEL)
    assert dev[1].dtype == np.bool_ and all(np.array_equal(a, b) for a, b in zip(host, dev, strict=True))
    with pytest.raises(EmptySurfaceError, match="no bone"):
        bone_and_skull_on(backend, data, float(data.max()) + 1.0)


def test_auto_keeps_the_hosts_tree_on_the_hosts_cpu_only(backend) -> None:
    from engine.defect import find_symmetry_plane
    from engine.defect.plane import skull_masks

    vol = _headsq_cut().volume
    host = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT)
    auto = find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device=backend)
    if backend.is_host:  # the tree's plane itself
        assert auto.normal_grid == host.normal_grid and auto.offset_grid_mm == host.offset_grid_mm
    else:  # a GPU's OpenCL: the device's
        assert _angle_deg(auto.normal_grid, host.normal_grid) < 0.1
    masks = skull_masks(vol.data, HEADSQ_LEVEL, backend, "device")
    assert all(np.array_equal(a, b) for a, b in zip(masks, skull_masks(vol.data, HEADSQ_LEVEL), strict=True))
    with pytest.raises(ValueError, match="where is one of"):
        find_symmetry_plane(vol, HEADSQ_LEVEL, orient=ORIENT, device=backend, where="gpu")
