"""Engine test fixtures: ``backend``, parametrised over the device backends (``engine.backend``) a test can run on
here: ``"warp-cpu"`` (Warp's CPU path) and ``"opencl"`` (the first OpenCL device: PoCL on the CPU in CI). A test
that takes ``backend`` runs once per backend; the OpenCL run skips, saying why, only where PyOpenCL or every OpenCL
platform is missing (CI installs PoCL, so it runs there)."""

from __future__ import annotations

import functools

import pytest

BACKENDS = ("warp-cpu", "opencl")


@functools.cache
def opencl_missing() -> str | None:
    """Why the OpenCL backend cannot run here, or None."""
    try:
        from engine.backend.select import opencl_devices

        if not opencl_devices():
            return "no OpenCL platform is installed (Debian: apt-get install pocl-opencl-icd)"
    except ValueError as exc:  # PyOpenCL is not installed
        return str(exc)
    return None


def backend_for(name: str):  # -> engine.backend.Backend
    """The backend a ``backend`` parameter names (skipping the test where it cannot run)."""
    from engine.backend import get_backend

    if name == "opencl":
        why = opencl_missing()
        if why is not None:
            pytest.skip(f"OpenCL backend: {why}")
        return get_backend("opencl")
    return get_backend("cpu")


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest):
    """Each device backend in turn (``engine.backend.Backend``)."""
    return backend_for(request.param)


@pytest.fixture
def opencl():
    """The OpenCL backend (skips, with the reason, where none can run)."""
    return backend_for("opencl")
