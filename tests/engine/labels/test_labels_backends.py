"""Label maps on every backend (issue 40): the per-label meshing is written once over ``engine.backend`` with an
OpenCL C twin of each Warp kernel, so OpenCL (PoCL here) gives Warp's CPU mesh bit for bit, and a label job (or a CT
job) on an OpenCL device launches no Warp kernel at all."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from engine.labels import mesh_labels
from engine.labels.extract import area_scale
from engine.params import DecimateParams, ReconParams
from tests.engine.conftest import backend_for


def _map(dtype: Any) -> np.ndarray:
    """Three labels on a small grid: two balls touching each other (a shared face) and a slab apart."""
    zz, yy, xx = np.mgrid[:30, :36, :34]
    lab = np.zeros((30, 36, 34), dtype)
    lab[((zz - 15) ** 2 + (yy - 14) ** 2 + (xx - 14) ** 2) < 64] = 3
    lab[(((zz - 14) ** 2 + (yy - 24) ** 2 + (xx - 20) ** 2) < 40) & (lab == 0)] = 200
    lab[4:9, 4:30, 24:31] = 2
    return lab


PARAMS = ReconParams(decimate=DecimateParams(reduction=0.3))


@pytest.fixture(scope="module")
def warp_mesh():
    return mesh_labels(_map(np.uint16), [2, 3, 200], (0.8, 0.5, 0.5), PARAMS, device=backend_for("warp-cpu"))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.uint32])
def test_opencl_gives_warps_mesh_bit_for_bit(warp_mesh, opencl, dtype) -> None:
    cl = mesh_labels(_map(dtype), [2, 3, 200], (0.8, 0.5, 0.5), PARAMS, device=opencl)
    assert cl.info["backend"] == opencl.label and warp_mesh.info["backend"].startswith("warp")
    assert cl.info["decimate"]["share_faces"] == warp_mesh.info["decimate"]["share_faces"]
    assert cl.info["decimate"]["output_faces"] == warp_mesh.info["decimate"]["output_faces"] < cl.info["mc33_faces"]
    assert np.array_equal(cl.faces, warp_mesh.faces) and np.array_equal(cl.slot, warp_mesh.slot)
    assert np.array_equal(cl.vertices, warp_mesh.vertices)
    assert cl.info["watertight"] and cl.info["manifold"] and sorted(set(cl.slot.tolist())) == [0, 1, 2]


def test_the_area_sums_are_exact_in_any_order() -> None:
    """Per-label areas are summed in fixed point: the same total whatever order the device adds faces in."""
    scale = area_scale((0.8, 0.5, 0.5))
    assert scale == 2.0**20 / 0.25
    areas = np.random.default_rng(1).uniform(0.01, 2.0, 10_000).astype(np.float32)
    units = (areas * np.float32(scale) + np.float32(0.5)).astype(np.int64)
    shuffled = units[np.random.default_rng(2).permutation(len(units))]
    assert int(np.cumsum(units)[-1]) == int(np.cumsum(shuffled)[-1])
    assert abs(units.sum() / scale - areas.astype(np.float64).sum()) < 1e-6 * areas.sum()


class _Launches:
    """Counts Warp kernel launches and OpenCL enqueues while installed."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import pyopencl as cl
        import warp as wp

        self.warp: list[str] = []
        self.opencl = 0
        real_wp, real_cl = wp.launch, cl.enqueue_nd_range_kernel

        def spy_wp(kernel: Any, *a: Any, **k: Any) -> Any:
            self.warp.append(getattr(kernel, "key", str(kernel)))
            return real_wp(kernel, *a, **k)

        def spy_cl(*a: Any, **k: Any) -> Any:
            self.opencl += 1
            return real_cl(*a, **k)

        monkeypatch.setattr(wp, "launch", spy_wp)
        monkeypatch.setattr(cl, "enqueue_nd_range_kernel", spy_cl)


def test_the_label_batch_on_opencl_launches_no_warp_kernel(opencl, monkeypatch) -> None:
    launches = _Launches(monkeypatch)
    out = mesh_labels(_map(np.uint8), [2, 3, 200], (0.8, 0.5, 0.5), PARAMS, device=opencl)
    assert len(out.faces) and launches.warp == [] and launches.opencl > 50


def test_a_label_job_on_opencl_launches_no_warp_kernel(opencl, tmp_path, monkeypatch) -> None:
    """The whole job: the map read, every label meshed, its files written (the preview drawn on the job's device)."""
    from engine.job import InputSpec, JobSpec, resolve_runtime, run_job
    from tests.engine.labels.test_labels_outputs import nifti_bytes
    from tests.engine.labels.test_labels_util import headsq_labels

    (tmp_path / "map.nii").write_bytes(nifti_bytes(headsq_labels()))
    runtime = resolve_runtime(opencl)
    launches = _Launches(monkeypatch)
    spec = JobSpec(recon=PARAMS, input=InputSpec(kind="labels"))
    result = run_job(tmp_path / "map.nii", tmp_path / "out", spec, runtime)
    assert result.plan == "labels" and len(result.report["labels"]) >= 2 and (tmp_path / "out" / "preview.png").exists()
    assert launches.warp == [] and launches.opencl > 0


def test_a_scan_job_on_opencl_launches_no_warp_kernel(opencl, tmp_path, monkeypatch) -> None:
    """A CT job: the pipeline, every file and the preview (the defect's own: defect/test_defect_backends.py)."""
    from engine.job import JobSpec, resolve_runtime, run_job
    from tests.engine.job.test_job import SMALL, _phantom

    runtime = resolve_runtime(opencl)
    launches = _Launches(monkeypatch)
    result = run_job(_phantom(), tmp_path / "out", JobSpec(recon=ReconParams.from_dict(SMALL)), runtime)
    assert result.plan == "scan" and (tmp_path / "out" / "preview.png").exists()
    assert launches.warp == [] and launches.opencl > 0
