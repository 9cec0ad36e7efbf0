"""The one place that maps a device spec ("auto", "cpu", "cuda", "cuda:N", "opencl", "opencl:N") to a Warp device
(``resolve_device``) and to the backend the device stages run on (``resolve_backend``, ``engine.backend``)."""

from __future__ import annotations

import os
import re
from typing import TYPE_CHECKING, Any, TypeAlias

if TYPE_CHECKING:  # pragma: no cover
    import warp as wp

    from engine.backend.base import Backend

DeviceSpec: TypeAlias = "str | wp.Device"  # "auto", "cpu", "cuda", "cuda:N", "opencl", "opencl:N", or a Warp device
_SPEC = re.compile(r"^(auto|cpu|cuda(:\d+)?|opencl(:\d+)?)$")
_initialized = False


def init_runtime(kernel_cache_dir: str | None = None) -> None:
    """Initialise Warp quietly (call in a worker child, never before fork).

    Warp's banner and module-load lines are silenced, and so is the native "no CUDA driver" warning that it
    writes to stderr on machines without a GPU: the engine reports the device it uses itself.
    """
    global _initialized
    if _initialized:
        return
    import warp as wp

    wp.config.log_level = 30  # warnings and above
    if kernel_cache_dir:
        wp.config.kernel_cache_dir = kernel_cache_dir
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    _initialized = True


def resolve_device(spec: Any = "auto") -> wp.Device:
    """Return the Warp device for ``spec``.

    Args:
        spec: "auto" (``engine.backend.select.auto_spec``: CUDA when present, else an OpenCL GPU, else the faster
            CPU path; Warp's CPU device where the stages run on OpenCL), "cpu", "cuda" or "cuda:N", or a Warp device
            (returned as is);
            "opencl" or "opencl:N" (N counts every OpenCL device of every platform, GPUs first, then accelerators,
            then CPUs: ``engine.backend.opencl_devices``) is checked to be present and gives Warp's CPU device, where
            the stages not yet written for OpenCL run (the Gaussian and MC33 run on ``resolve_backend(spec)``).

    Raises:
        ValueError: the spec is malformed or names a CUDA device that is not present; for "opencl[:N]", PyOpenCL,
            any OpenCL platform or device N is missing.
    """
    if not isinstance(spec, str):
        import warp as wp

        if isinstance(spec, wp.Device):  # Warp's public name (``warp.context`` is gone from Warp 1.19's namespace)
            return spec
    if not isinstance(spec, str) or not _SPEC.match(spec):
        raise ValueError(f"Expected device 'auto', 'cpu', 'cuda', 'cuda:N', 'opencl' or 'opencl:N', got {spec!r}")
    if spec == "auto" and _auto_is_opencl():
        spec = "cpu"  # the device stages run on OpenCL (resolve_backend); Warp's own steps on its CPU path
    if spec.startswith("opencl"):
        from engine.backend.select import opencl_index

        opencl_index(spec)  # present, or a clear ValueError
        spec = "cpu"
    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    import warp as wp

    if spec == "auto":
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    if spec.startswith("cuda"):
        n = wp.get_cuda_device_count()
        index = int(spec.split(":")[1]) if ":" in spec else 0
        if index >= n:
            raise ValueError(f"Expected an available CUDA device ({n} present), got {spec!r}")
        return wp.get_device(f"cuda:{index}")
    return wp.get_device("cpu")


def _auto_is_opencl() -> bool:
    from engine.backend.select import auto_spec

    return auto_spec().startswith("opencl")


def resolve_backend(spec: Any = "auto") -> Backend:
    """The backend (``engine.backend.Backend``) the device stages run on for ``spec``: OpenCL for "opencl[:N]",
    else Warp on ``resolve_device(spec)``'s device (a backend is returned as is).

    Raises:
        ValueError: as ``resolve_device``.
    """
    from engine.backend.select import get_backend

    return get_backend(spec)


def cuda_available() -> bool:
    """True when Warp sees at least one CUDA device."""
    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    import warp as wp

    return wp.get_cuda_device_count() > 0
