"""``engine.device.resolve_device``: specs map to Warp devices; a Warp device is returned as it is."""

from __future__ import annotations

import numpy as np
import pytest

from engine.device import resolve_device


def test_a_warp_device_is_returned_as_is(device):
    """Warp 1.19 has no ``wp.context``: the check names ``wp.Device``, so a device object passes straight through."""
    import warp as wp

    dev = wp.get_device(device)
    assert resolve_device(dev) is dev
    assert resolve_device(device) is dev


def test_reconstruct_takes_a_warp_device(device):
    import warp as wp

    from engine.job.pipeline import reconstruct
    from engine.params import ReconParams
    from engine.types import Volume

    z, y, x = np.mgrid[:20, :20, :20].astype(np.float32)
    ball = Volume(6.0 - np.sqrt((z - 9.5) ** 2 + (y - 9.5) ** 2 + (x - 9.5) ** 2), (1.0, 1.0, 1.0))
    params = ReconParams.from_dict({"iso": {"iso": 0.0}, "body": None})
    by_object = reconstruct(ball, params, device=wp.get_device(device))
    by_name = reconstruct(ball, params, device=device)
    assert by_object.report["device"]["name"] == str(wp.get_device(device))
    assert by_object.report["device"]["spec"] == str(wp.get_device(device))  # the report stays JSON-able
    np.testing.assert_array_equal(by_object.mesh.faces, by_name.mesh.faces)
    np.testing.assert_array_equal(by_object.mesh.vertices, by_name.mesh.vertices)


@pytest.mark.parametrize("spec", ["tpu", "cuda:x", "", 3, None])
def test_a_malformed_spec_is_refused(spec):
    with pytest.raises(ValueError, match="Expected device"):
        resolve_device(spec)


class _Runtime:
    """Warp's runtime as it is on a machine whose NVIDIA driver is too old for Warp's CUDA build (or whatever the
    test sets)."""

    is_cuda_enabled = True
    toolkit_version = (13, 0)
    min_driver_version = (13, 0)
    driver_version: tuple[int, int] | None = (12, 2)


@pytest.fixture
def no_cuda(monkeypatch, tmp_path):
    """No CUDA device, Warp's runtime versions and the kernel driver's version file as the test sets them."""
    import warp as wp

    from engine.backend import warp_device

    rt = _Runtime()
    proc = tmp_path / "version"
    proc.write_text("NVRM version: NVIDIA UNIX x86_64 Kernel Module  535.104.05  Sat Aug 19 01:15:15 UTC 2023\n")
    monkeypatch.setattr(warp_device, "_warp_runtime", lambda: rt)
    monkeypatch.setattr(warp_device, "NVIDIA_PROC", proc)
    monkeypatch.setattr(wp, "get_cuda_device_count", lambda: 0)
    return rt, proc


def test_a_driver_too_old_for_warp_is_named_with_the_one_needed(no_cuda) -> None:
    import warp as wp

    from engine.backend.warp_device import cuda_problem, warp_device

    nvidia, why = cuda_problem()
    assert nvidia
    assert why == (
        f"the NVIDIA driver 535.104.05 supports CUDA 12.2, but Warp {wp.__version__} (built with CUDA 13.0) "
        "needs a driver for CUDA 13.0 or newer "
        "(Linux: 580.65.06 or later): update the NVIDIA driver"
    )
    with pytest.raises(ValueError, match=r"\(0 present\), got 'cuda:0': the NVIDIA driver 535.104.05 supports"):
        warp_device("cuda:0")


def test_auto_says_loudly_why_the_gpu_is_passed_over(no_cuda) -> None:
    from engine.job.runtime import _auto_reason

    assert _auto_reason("cpu").endswith(
        "CUDA is unusable: " + __import__("engine").backend.warp_device.cuda_problem()[1]
    )


def test_a_kernel_driver_without_its_library_and_no_driver_at_all(no_cuda) -> None:
    from engine.backend.warp_device import cuda_problem

    rt, proc = no_cuda
    rt.driver_version = None
    assert cuda_problem() == (
        True,
        "the NVIDIA kernel driver 535.104.05 is loaded, but its CUDA library (libcuda.so.1) could not be loaded "
        "(in a container: start it with the NVIDIA Container Toolkit, e.g. --gpus all)",
    )
    proc.unlink()
    assert cuda_problem() == (False, "no NVIDIA GPU driver is loaded on this machine")


def test_a_cuda_worker_without_a_usable_gpu_does_not_start() -> None:
    """``bonemesh worker --device cuda:0`` for real (its probe a process of its own) on this machine: exit 2, one
    line with the reason, no worker started."""
    import subprocess

    from engine.backend.warp_device import cuda_available
    from tests.service.procs import bonemesh_argv

    if cuda_available():
        pytest.skip("this machine has a CUDA GPU")
    done = subprocess.run(
        [*bonemesh_argv(), "worker", "--device", "cuda:0"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("bonemesh worker: cuda:0 is not usable: ") and done.stderr.count("\n") == 1
