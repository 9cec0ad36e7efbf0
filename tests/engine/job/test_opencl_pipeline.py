"""The whole pipeline on OpenCL (issue 28): ``reconstruct`` and ``write_outputs`` with ``device="opencl"`` (PoCL in
CI) give the model of Warp's CPU path bit for bit, whole and streamed in slabs within a memory budget, and every
file but the report the same bytes; the report names the backend and device; ``auto`` resolves as documented."""

from __future__ import annotations

import hashlib
import json

import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.params import IsoParams, ReconParams
from tests.engine.conftest import opencl_missing

pytestmark = pytest.mark.skipif(opencl_missing() is not None, reason=f"OpenCL backend: {opencl_missing()}")


@pytest.fixture(scope="module")
def headsq():
    from engine.io import load_volume

    return load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)


def _digest(recon) -> str:
    m = recon.mesh
    return hashlib.sha256(m.vertices.tobytes() + m.faces.tobytes() + m.normals.tobytes()).hexdigest()


@pytest.mark.parametrize("budget", [None, "6MiB"], ids=["whole", "streamed"])
def test_reconstruct_on_opencl_is_warps_model_bit_for_bit(headsq, budget):
    from engine.job.pipeline import reconstruct

    params = ReconParams(iso=IsoParams(iso=HEADSQ_LEVEL))
    warp = reconstruct(headsq, params, device="cpu", max_device_bytes=budget)
    ocl = reconstruct(headsq, params, device="opencl", max_device_bytes=budget)
    assert _digest(ocl) == _digest(warp)
    assert ocl.report["mesh"] == warp.report["mesh"] and ocl.report["mesh"]["watertight"]
    assert ocl.report["device"]["backend"] == "opencl" and ocl.report["device"]["name"].startswith("opencl:")
    assert warp.report["device"]["backend"] == "warp"
    assert ocl.report["decimate"]["method"].startswith("opencl")
    assert ocl.report["memory"]["peak_bytes"] > 0
    if budget is not None:
        assert ocl.report["memory"]["peak_bytes"] <= 6 << 20 and ocl.report["isosurface"]["slabs"] > 1


def test_write_outputs_on_opencl_writes_warps_files(headsq, tmp_path):
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    params = ReconParams(iso=IsoParams(iso=HEADSQ_LEVEL))
    files = {}
    for device in ("cpu", "opencl"):
        recon = reconstruct(headsq, params, device=device)
        paths = write_outputs(recon, tmp_path / device, params, device=device)
        files[device] = {name: p.read_bytes() for name, p in paths.items()}
    assert set(files["cpu"]) == set(files["opencl"])
    for name in files["cpu"]:
        if name != "report.json":  # it names the device and the times
            assert files["opencl"][name] == files["cpu"][name], name
    report = json.loads(files["opencl"]["report.json"])
    assert report["layout"]["device"].startswith("opencl:")


def test_auto_prefers_cuda_then_an_opencl_gpu_then_the_faster_cpu_path():
    from engine.backend.select import CPU_AUTO, auto_spec, opencl_devices
    from engine.device import cuda_available, resolve_backend

    spec = auto_spec()
    if cuda_available():
        assert spec == "cuda"
    elif any(d.type & 4 for d in opencl_devices()):  # CL_DEVICE_TYPE_GPU
        assert spec.startswith("opencl:")
    else:
        assert spec == ("opencl:0" if CPU_AUTO == "opencl" else "cpu")
    assert resolve_backend("auto") is resolve_backend(spec)
