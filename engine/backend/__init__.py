"""The device backends the host stages call (``Backend``): Warp (``WarpBackend``: CUDA or Warp's CPU path) and
OpenCL through PyOpenCL (``OpenCLBackend``: PoCL on the CPU, any GPU platform).

A host stage is written once over ``Backend``: it allocates, copies, launches named kernels (``Kernel``: one name, a
Warp kernel and an OpenCL C function), scans, compacts and synchronises through it; only kernels are written per
backend. ``get_backend(spec)`` maps a device spec ("auto", "cpu", "cuda[:N]", a Warp device, "opencl[:N]") to its
backend, ``backend_of(array)`` finds the backend of a device array. See docs/opencl.md.

Public names load lazily (``engine._lazy``): importing this package loads neither Warp nor PyOpenCL.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.backend.base import VEC3F, VEC3I, Backend, Kernel, PeakTracker, Struct
    from engine.backend.select import backend_of, get_backend, opencl_devices

__all__ = [
    "VEC3F",
    "VEC3I",
    "Backend",
    "Kernel",
    "PeakTracker",
    "Struct",
    "backend_of",
    "get_backend",
    "opencl_devices",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "VEC3F": ".base",
        "VEC3I": ".base",
        "Backend": ".base",
        "Kernel": ".base",
        "PeakTracker": ".base",
        "Struct": ".base",
        "backend_of": ".select",
        "get_backend": ".select",
        "opencl_devices": ".select",
    },
)
