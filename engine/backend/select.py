"""Which backend a device spec means (``get_backend``), which backend an array lives on (``backend_of``), and the
OpenCL devices in the order ``"opencl:N"`` counts them (``opencl_devices``)."""

from __future__ import annotations

import functools
import os
import re
from typing import Any

from engine.backend.base import Backend

_OPENCL = re.compile(r"^opencl(:(\d+))?$")
SPEC = re.compile(r"^(auto|cpu|cuda(:\d+)?|opencl(:\d+)?)$")  # the device specs every edge accepts
_MISSING_PYOPENCL = (
    "device 'opencl' needs PyOpenCL: install the engine's `opencl` extra (pip install 'bonemesh[opencl]') and an "
    "OpenCL driver (Debian: pocl-opencl-icd for the CPU; a GPU vendor's ICD)"
)


def is_opencl_spec(spec: Any) -> bool:
    """True for ``"opencl"`` and ``"opencl:N"``."""
    return isinstance(spec, str) and _OPENCL.match(spec) is not None


# PoCL compiles a kernel again for every new launch size unless told not to; the decimation's launch sizes change
# every pass (a fresh cache: 88 s for one tiled decimation of headsq, 3 s without; steady state ~10 % slower)
POCL_DEFAULTS = {"POCL_WORK_GROUP_SPECIALIZATION": "0"}


def _import_pyopencl() -> Any:
    for name, value in POCL_DEFAULTS.items():  # read when PoCL loads (the first platform query): set before it
        os.environ.setdefault(name, value)
    try:
        import pyopencl as cl
    except ImportError as exc:
        raise ValueError(f"{_MISSING_PYOPENCL} ({exc})") from None
    return cl


@functools.cache
def opencl_devices() -> tuple[Any, ...]:
    """Every OpenCL device of every platform, GPUs first, then accelerators, then CPUs (each group in platform
    order, then the platform's device order): ``"opencl:N"`` is the N-th. Empty where no platform is installed.

    Raises:
        ValueError: PyOpenCL is not installed.
    """
    cl = _import_pyopencl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # PLATFORM_NOT_FOUND_KHR: the ICD loader found no driver
        return ()
    found = []
    for p_index, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except cl.Error:  # a platform with no device
            continue
        for d_index, dev in enumerate(devices):
            rank = 0 if dev.type & cl.device_type.GPU else 1 if dev.type & cl.device_type.ACCELERATOR else 2
            found.append(((rank, p_index, d_index), dev))
    return tuple(dev for _, dev in sorted(found, key=lambda item: item[0]))


def opencl_index(spec: str) -> int:
    """The device index ``"opencl:N"`` names (0 for ``"opencl"``), checked against the devices present.

    Raises:
        ValueError: PyOpenCL, any OpenCL platform, or device N is missing.
    """
    m = _OPENCL.match(spec)
    if m is None:
        raise ValueError(f"Expected device 'opencl' or 'opencl:N', got {spec!r}")
    index = int(m.group(2) or 0)
    devices = opencl_devices()
    if not devices:
        raise ValueError(
            f"device {spec!r}: no OpenCL platform is installed (the ICD loader found no driver; Debian: "
            "apt-get install pocl-opencl-icd for the CPU, or a GPU vendor's OpenCL driver)"
        )
    if index >= len(devices):
        names = ", ".join(f"opencl:{i} {d.name.strip()}" for i, d in enumerate(devices))
        raise ValueError(f"Expected an available OpenCL device ({len(devices)} present: {names}), got {spec!r}")
    return index


@functools.cache
def _opencl_backend(index: int) -> Backend:
    from engine.backend.opencl_backend import OpenCLBackend

    return OpenCLBackend(opencl_devices()[index], index)


# "auto" on a host without CUDA or an OpenCL GPU: the faster CPU path, by measurement (benchmarks/backends.py,
# docs/opencl.md): "opencl" (PoCL on every core) where a CPU OpenCL device is installed, else Warp's one thread
CPU_AUTO = "opencl"


@functools.cache
def auto_spec() -> str:
    """What ``"auto"`` means on this host: CUDA where Warp sees a GPU, else the first OpenCL GPU, else the faster CPU
    path (``CPU_AUTO``: an OpenCL CPU device where one is installed), else Warp's CPU ("cpu")."""
    from engine.backend.warp_device import cuda_available

    if cuda_available():
        return "cuda"
    try:
        devices = opencl_devices()
    except ValueError:  # PyOpenCL is not installed
        return "cpu"
    cl = _import_pyopencl()
    for i, dev in enumerate(devices):
        if dev.type & cl.device_type.GPU:
            return f"opencl:{i}"
    if CPU_AUTO == "opencl" and devices:
        return "opencl:0"
    return "cpu"


def get_backend(spec: Any = "auto") -> Backend:
    """The backend of a device spec: ``"opencl"`` / ``"opencl:N"`` (``opencl_devices``' order) gives the OpenCL
    backend (one per device and process, its programs built once); ``"auto"``, ``"cpu"``, ``"cuda[:N]"`` or a Warp
    device gives the Warp backend on that device (``engine.backend.warp_device``); a ``Backend`` is returned as is.

    Raises:
        ValueError: a malformed spec, or a device (or PyOpenCL, or any OpenCL platform) that is not present.
    """
    if isinstance(spec, Backend):
        return spec
    if not isinstance(spec, str):
        import warp as wp

        if isinstance(spec, wp.Device):  # Warp's public name (``warp.context`` is gone from Warp 1.19's namespace)
            return _warp_backend(spec)
    if not isinstance(spec, str) or not SPEC.match(spec):
        raise ValueError(f"Expected device 'auto', 'cpu', 'cuda', 'cuda:N', 'opencl' or 'opencl:N', got {spec!r}")
    if spec == "auto":
        spec = auto_spec()
    if is_opencl_spec(spec):
        return _opencl_backend(opencl_index(spec))
    from engine.backend.warp_device import warp_device

    return _warp_backend(warp_device(spec))


_WARP: dict[str, Backend] = {}


def _warp_backend(device: Any) -> Backend:
    """One Warp backend per Warp device (keyed by its name: ``wp.Device`` is not hashable)."""
    key = str(device)
    if key not in _WARP:
        from engine.backend.warp_backend import WarpBackend

        _WARP[key] = WarpBackend(device)
    return _WARP[key]


def backend_of(arr: Any) -> Backend:
    """The backend a device array lives on (an OpenCL ``CLArray``'s own, else Warp's for a ``wp.array``)."""
    owner = getattr(arr, "backend", None)
    if isinstance(owner, Backend):
        return owner
    return _warp_backend(arr.device)
