"""Device specs ("auto", "cpu", "cuda", "cuda:N", "opencl", "opencl:N") as the engine's functions accept them:
``resolve_backend`` (the backend the device stages run on, ``engine.backend.select.get_backend``) and
``resolve_device`` (the Warp device of Warp's own steps: Warp's CPU where the stages run on OpenCL).

A job resolves its spec once, at its edge, into an ``engine.job.Runtime`` and passes its ``Backend`` down; both
functions return what a ``Backend`` (or a Warp device) already names without looking anything up again. The layers
below this module (``engine.backend.warp_device``, ``engine.backend.select``) never import it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeAlias

from engine.backend.warp_device import cuda_available, init_runtime

if TYPE_CHECKING:  # pragma: no cover
    import warp as wp

    from engine.backend.base import Backend

__all__ = ["DeviceSpec", "cuda_available", "init_runtime", "resolve_backend", "resolve_device"]

# "auto", "cpu", "cuda", "cuda:N", "opencl", "opencl:N", a Warp device, or a Backend (resolved already)
DeviceSpec: TypeAlias = "str | wp.Device | Backend"


def resolve_device(spec: Any = "auto") -> wp.Device:
    """Return the Warp device for ``spec``.

    Args:
        spec: "auto" (``engine.backend.select.auto_spec``: CUDA when present, else an OpenCL GPU, else the faster
            CPU path; Warp's CPU device where the stages run on OpenCL), "cpu", "cuda" or "cuda:N", a Warp device
            (returned as is), a ``Backend`` (its Warp device; Warp's CPU for an OpenCL one), or "opencl" /
            "opencl:N" (N counts every OpenCL device of every platform, GPUs first, then accelerators, then CPUs:
            ``engine.backend.opencl_devices``), checked to be present, which gives Warp's CPU device.

    Raises:
        ValueError: the spec is malformed or names a CUDA device that is not present; for "opencl[:N]", PyOpenCL,
            any OpenCL platform or device N is missing.
    """
    from engine.backend.select import get_backend

    device: wp.Device = _warp_device_of(get_backend(spec))
    return device


def _warp_device_of(backend: Backend) -> Any:
    """A Warp backend's device; Warp's CPU device for another backend (Warp's own steps beside OpenCL)."""
    if backend.kind == "warp":
        return backend.device  # type: ignore[attr-defined]
    from engine.backend.warp_device import warp_device

    return warp_device("cpu")


def resolve_backend(spec: Any = "auto") -> Backend:
    """The backend (``engine.backend.Backend``) the device stages run on for ``spec``: OpenCL for "opencl[:N]",
    else Warp on ``resolve_device(spec)``'s device (a backend is returned as is).

    Raises:
        ValueError: as ``resolve_device``.
    """
    from engine.backend.select import get_backend

    return get_backend(spec)
