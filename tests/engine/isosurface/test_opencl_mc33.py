"""The Gaussian and Marching Cubes 33 on OpenCL (``engine.backend``, PoCL in CI) give the same results as on Warp's
CPU path: the same vertices and faces in the same order (bit for bit), cell by cell and on real scans; the Gaussian
bit for bit. The Warp CPU run is the reference; each comparison runs both backends on the same input."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.isosurface import IsosurfaceStats, extract_isosurface, marching_cubes_33
from engine.params import GaussianParams
from engine.volume.gaussian import smooth_volume
from tests.engine.isosurface.test_mc33_cells import _check_cell, _draws

HEADSQ_LEVEL = 1150.0


def _same_mesh(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> None:
    assert a[0].dtype == b[0].dtype and a[1].dtype == b[1].dtype
    np.testing.assert_array_equal(a[1], b[1])  # the same faces, in the same order
    np.testing.assert_array_equal(a[0], b[0])  # the same vertices, bit for bit


def _both(vol: np.ndarray, level: float, **kw) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    return marching_cubes_33(vol, level, device="cpu", **kw), marching_cubes_33(vol, level, device="opencl", **kw)


@functools.cache
def _headsq() -> np.ndarray:
    from engine.io.stack import load_slice_zip

    return load_slice_zip(HEADSQ_ZIP)


def test_the_kernels_block_size_is_the_hosts():
    from engine.isosurface.kernel_specs import BLOCK
    from engine.isosurface.kernels import mc33 as warp_kernels

    source = Path(warp_kernels.__file__ or "").with_name("mc33.cl")
    assert warp_kernels.BLOCK == BLOCK
    assert f"#define BLOCK {BLOCK}\n" in source.read_text()


def test_every_drawn_cell_gives_the_same_mesh_and_the_reference_topology(opencl):
    """One draw per (sign configuration, MC33 subcase), each a 2x2x2 volume, on both backends: the same mesh, and
    the OpenCL mesh passes the cell test's topology check against the trilinear reference."""
    firsts = {}
    for d in _draws():
        firsts.setdefault((d.mask, d.subcase), d)
    assert len(firsts) > 500
    for d in firsts.values():
        vol = d.values.reshape(2, 2, 2)  # corner i = x + 2y + 4z
        warp_mesh, cl_mesh = _both(vol, 0.0, closed=False)
        _same_mesh(warp_mesh, cl_mesh)
        assert not _check_cell(*cl_mesh, d.topo), (d.mask, d.subcase)


def test_all_drawn_cells_packed_in_one_volume_give_the_same_mesh(opencl):
    """Every draw of the cell tests (about 6,300), each the 2x2x2 samples of its own cell in one volume (the cells
    between them are mixed draws): the same mesh on both backends, open and closed."""
    draws = _draws()
    side = int(np.ceil(len(draws) ** (1 / 3)))
    vol = np.full((2 * side, 2 * side, 2 * side), -1.0, np.float32)
    for k, d in enumerate(draws):
        z, y, x = np.unravel_index(k, (side, side, side))
        vol[2 * z : 2 * z + 2, 2 * y : 2 * y + 2, 2 * x : 2 * x + 2] = d.values.reshape(2, 2, 2)
    for closed in (False, True):
        warp_mesh, cl_mesh = _both(vol, 0.0, closed=closed)
        assert len(warp_mesh[1]) > len(draws)
        _same_mesh(warp_mesh, cl_mesh)


def test_the_published_mc33_cases_give_the_same_mesh(opencl):
    import json

    from tests.conftest import shared_file

    cases = json.loads(shared_file("mc33_cases", "cases.json").read_text())
    assert cases
    for name in cases:
        vol = np.load(shared_file("mc33_cases", f"{name}.npy"))
        for closed in (False, True):
            _same_mesh(*_both(vol, 0.0, closed=closed))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.float32])
def test_the_gaussian_is_bit_for_bit_the_same(opencl, dtype):
    from engine.backend import get_backend

    rng = np.random.default_rng(28)
    vol = (rng.random((9, 13, 17)) * 200).astype(dtype)
    warp = get_backend("cpu")
    ref = warp.to_host(smooth_volume(warp.from_host(vol), GaussianParams(sigma_voxels=0.8)))
    got = opencl.to_host(smooth_volume(opencl.from_host(vol), GaussianParams(sigma_voxels=0.8)))
    assert got.dtype == np.float32 and got.shape == vol.shape
    np.testing.assert_array_equal(got, ref)


def test_headsq_smoothed_and_extracted_on_the_device_is_the_same_mesh(backend):
    """The pipeline's volume stages on the device (Gaussian, then MC33 on the field in several slabs): the same mesh
    as Warp's CPU path, on every backend; the slabs change nothing."""
    from engine.backend import get_backend

    vol = _headsq()
    meshes = {}
    for be in (get_backend("cpu"), backend):
        field = smooth_volume(be.from_host(vol), GaussianParams())
        for budget in (None, 400_000):  # the whole field in one slab, or several (views of the field)
            st = IsosurfaceStats()
            v, f = extract_isosurface(
                field, HEADSQ_LEVEL, spacing=HEADSQ_SPACING_ZYX_MM, closed=True, max_device_bytes=budget, stats=st
            )
            assert st.slabs == 1 or budget is not None
            meshes[(be.kind, budget)] = (be.to_host(v).reshape(-1, 3), be.to_host(f).reshape(-1, 3))
    ref = meshes[("warp", None)]
    assert len(ref[1]) > 10_000
    for mesh in meshes.values():
        _same_mesh(ref, mesh)


def test_headsq_from_the_host_in_slabs_is_the_same_mesh(opencl):
    vol = _headsq()
    for budget in (None, 300_000):
        st, warp_st = IsosurfaceStats(), IsosurfaceStats()
        kw = {"spacing": HEADSQ_SPACING_ZYX_MM, "closed": False, "max_device_bytes": budget}
        warp_mesh = marching_cubes_33(vol, HEADSQ_LEVEL, device="cpu", stats=warp_st, **kw)
        cl_mesh = marching_cubes_33(vol, HEADSQ_LEVEL, device="opencl", stats=st, **kw)
        assert st.table_misses == 0 and st.level_in_range
        assert budget is None or st.slabs > 1
        assert st == warp_st  # the same slabs, blocks, retries and working set: the host plan is the same code
        _same_mesh(warp_mesh, cl_mesh)


def test_nan_and_a_level_outside_the_data_on_opencl(opencl):
    vol = np.zeros((6, 6, 6), np.float32)
    assert len(marching_cubes_33(vol, 5.0, device="opencl")[1]) == 0  # level above every sample: empty
    vol[3, 3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        marching_cubes_33(vol, 0.5, device="opencl")


def test_device_results_stay_on_their_backend(backend):
    vol = np.zeros((5, 5, 5), np.uint8)
    vol[1:4, 1:4, 1:4] = 9
    v, f = extract_isosurface(backend.from_host(vol), 4.0, closed=True)
    from engine.backend import backend_of

    assert backend_of(v) is backend and backend_of(f) is backend
    assert backend.to_host(f).shape == (len(f), 3)
