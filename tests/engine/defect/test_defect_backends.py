"""The defect template on every backend (issue 40): its device work (the distance transform, the mirror and the
voxel rules, ``engine.defect.kernels``) and the preview's rasteriser (``engine.export.preview``) are written once
over ``engine.backend`` with a Warp kernel and an OpenCL C twin each; Warp's CPU and OpenCL give the same answer,
and a job on OpenCL runs no Warp kernel."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.params import OrientParams

ORIENT = OrientParams(first_slice="superior")


@functools.cache
def _cut() -> Any:
    """headsq (93 x 64 x 64) with a 30 mm trephination at the left temple."""
    from engine.defect.synthetic import cut_defect
    from engine.io import load_volume

    headsq = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    return cut_defect(headsq, HEADSQ_LEVEL, (1.0, -0.1, 0.0), 30.0, slices=(4, 18), orient=ORIENT)


def _defect(device: Any) -> Any:
    from engine.defect import DefectParams, run

    return run(_cut().volume, DefectParams(), HEADSQ_LEVEL, device, orient=ORIENT)


class _Launches:
    """Counts OpenCL enqueues; a Warp launch (``warp.launch`` or Warp's own internal ``launch``) raises."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import pyopencl as cl
        import warp as wp
        import warp._src.context as wp_context

        self.opencl = 0
        real_cl = cl.enqueue_nd_range_kernel

        def no_warp(kernel: Any, *a: Any, **k: Any) -> Any:
            raise AssertionError(f"a Warp kernel was launched: {getattr(kernel, 'key', kernel)}")

        def spy_cl(*a: Any, **k: Any) -> Any:
            self.opencl += 1
            return real_cl(*a, **k)

        monkeypatch.setattr(wp, "launch", no_warp)
        monkeypatch.setattr(wp_context, "launch", no_warp)
        monkeypatch.setattr(cl, "enqueue_nd_range_kernel", spy_cl)


def test_the_defect_is_the_same_on_warp_cpu_and_opencl(opencl) -> None:
    from engine.defect.template import implant_stl

    cpu, ocl = _defect("cpu"), _defect(opencl)
    assert int(cpu.mask.sum()) > 0
    assert np.array_equal(cpu.mask, ocl.mask) and cpu.mask_lo == ocl.mask_lo
    assert [(p.voxels, p.reason, p.kept) for p in cpu.pieces] == [(p.voxels, p.reason, p.kept) for p in ocl.pieces]
    assert abs(cpu.volume_mm3 - ocl.volume_mm3) <= 1e-6 * cpu.volume_mm3
    assert cpu.to_json()["defect"] == ocl.to_json()["defect"]
    assert cpu.tissue == ocl.tissue and cpu.shell_mm == ocl.shell_mm
    assert implant_stl(cpu) == implant_stl(ocl)  # the same template, byte for byte


def test_a_defect_on_opencl_launches_no_warp_kernel(opencl, monkeypatch) -> None:
    _defect(opencl)  # the programs built first: the count is of one run
    launches = _Launches(monkeypatch)
    res = _defect(opencl)
    assert res.mask.any() and launches.opencl > 0


def test_the_distance_transform_is_exact_and_the_same_on_every_backend(backend) -> None:
    from scipy import ndimage as ndi

    from engine.defect.ops import BIG_MM, distance, upload_mask

    rng = np.random.default_rng(7)
    shape, sp = (9, 13, 11), (1.5, 0.7, 0.9)
    mask = rng.random(shape) < 0.05
    mask[4, 6, 5] = True
    got = {}
    for inside in (False, True):
        d = distance(backend, upload_mask(backend, mask), shape, sp, inside=inside)
        got[inside] = backend.to_host(d).reshape(shape)
        ref = ndi.distance_transform_edt(mask if inside else ~mask, sampling=sp)
        np.testing.assert_allclose(got[inside], ref, rtol=1e-5, atol=1e-5)
    empty = distance(backend, upload_mask(backend, np.zeros(shape, bool)), shape, sp)
    assert np.all(backend.to_host(empty) == np.float32(BIG_MM))
    if backend.kind == "opencl":
        from engine.backend import get_backend

        cpu = get_backend("cpu")
        for inside in (False, True):
            d = distance(cpu, upload_mask(cpu, mask), shape, sp, inside=inside)
            assert np.array_equal(cpu.to_host(d).reshape(shape), got[inside])  # bit for bit


def _mesh() -> tuple[Any, Any, Any]:
    """An icosphere-ish closed mesh with a dent (overlapping depths, ties)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    v = np.asarray(m.vertices, dtype=np.float64).copy()
    v[v[:, 2] > 6.0, 2] *= 0.5
    return v, np.asarray(m.faces, dtype=np.int32), np.asarray(m.vertex_normals, dtype=np.float64)


def test_the_preview_png_is_the_same_bytes_on_every_backend(opencl) -> None:
    import io

    import imageio.v3 as iio

    from engine.export.preview import render

    v, f, n = _mesh()
    cpu = render(v, f, n, 96, device="cpu")
    ocl = render(v, f, n, 96, device=opencl)
    assert cpu[..., 3].any()
    assert np.array_equal(cpu, ocl)
    png = []
    for img in (cpu, ocl):
        buf = io.BytesIO()
        iio.imwrite(buf, img, extension=".png")
        png.append(buf.getvalue())
    assert png[0] == png[1]


def test_the_preview_z_buffer_in_two_passes_is_the_one_pass_buffer(opencl) -> None:
    """OpenCL without 64-bit atomics: the depth, then the triangle at that depth, give the same z-buffer."""
    from engine.export.preview import rasterize

    rng = np.random.default_rng(3)
    n, m = 40, 300
    px, py = rng.uniform(-2, n + 2, m), rng.uniform(-2, n + 2, m)
    depth = np.round(rng.uniform(0, 1, m), 1)  # few depths: ties between triangles
    tris = rng.integers(0, m, (200, 3)).astype(np.int32)
    one = rasterize("cpu", px, py, depth, tris, n)
    assert (one != np.iinfo(np.int64).max).sum() > 100
    assert np.array_equal(rasterize(opencl, px, py, depth, tris, n, two_pass=False), one)
    assert np.array_equal(rasterize(opencl, px, py, depth, tris, n, two_pass=True), one)
