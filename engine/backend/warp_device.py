"""Warp's runtime and devices, below the backend choice (``engine.backend.select``) and the device specs
(``engine.device``): ``init_runtime`` (Warp initialised quietly, once), ``cuda_available`` and ``warp_device`` (a
concrete ``"cpu"`` / ``"cuda"`` / ``"cuda:N"`` spec to a ``wp.Device``). Imports nothing of the engine, so the
modules above it import it without a cycle."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from typing import Any

_initialized = False
NVIDIA_PROC = Path("/proc/driver/nvidia/version")  # present where the NVIDIA kernel driver is loaded
# the oldest Linux driver of each CUDA major version (NVIDIA's CUDA Toolkit release notes, table 3)
DRIVER_FOR_CUDA = {11: "450.80.02", 12: "525.60.13", 13: "580.65.06"}


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


def cuda_available() -> bool:
    """True when Warp sees at least one CUDA device."""
    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    import warp as wp

    return wp.get_cuda_device_count() > 0


def warp_device(spec: str) -> Any:
    """The ``wp.Device`` of a concrete spec: ``"cpu"``, ``"cuda"`` (device 0) or ``"cuda:N"``.

    Raises:
        ValueError: a CUDA device that is not present.
    """
    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    import warp as wp

    if spec.startswith("cuda"):
        n = wp.get_cuda_device_count()
        index = int(spec.split(":")[1]) if ":" in spec else 0
        if index >= n:
            why = cuda_problem()[1] if n == 0 else ""
            raise ValueError(
                f"Expected an available CUDA device ({n} present), got {spec!r}{': ' + why if why else ''}"
            )
        return wp.get_device(f"cuda:{index}")
    return wp.get_device("cpu")


def _kernel_driver() -> str | None:
    """The loaded NVIDIA kernel driver's version (``/proc/driver/nvidia/version``), or None."""
    try:
        text = NVIDIA_PROC.read_text()
    except OSError:
        return None
    match = re.search(r"\s(\d{3,}\.\d+(?:\.\d+)?)\s", text)
    return match.group(1) if match else "of unknown version"


def _warp_runtime() -> Any:
    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    from warp._src import context  # the runtime's versions have no public name

    return context.runtime


def cuda_problem() -> tuple[bool, str]:
    """Whether an NVIDIA driver is loaded here, and why Warp cannot use CUDA ("" where it sees a device): a driver
    older than the one Warp's CUDA build needs (Warp mutes its own warning about it), a kernel driver without its
    user-space library (a container started without the NVIDIA runtime), a CPU-only Warp build, no GPU at all."""
    import warp as wp

    rt = _warp_runtime()
    if wp.get_cuda_device_count() > 0:
        return True, ""
    kernel = _kernel_driver()
    named = f" {kernel}" if kernel else ""
    if not getattr(rt, "is_cuda_enabled", False):
        return kernel is not None, f"Warp {wp.__version__} is a build without CUDA (install warp-lang from PyPI)"
    tk, need, have = rt.toolkit_version, rt.min_driver_version, rt.driver_version
    if have is not None and need is not None and have < need:
        linux = DRIVER_FOR_CUDA.get(need[0])
        return True, (
            f"the NVIDIA driver{named} supports CUDA {have[0]}.{have[1]}, but Warp {wp.__version__} (built "
            f"with CUDA {tk[0]}.{tk[1]}) needs a driver for CUDA {need[0]}.{need[1]} or newer"
            f"{f' (Linux: {linux} or later)' if linux else ''}: update the NVIDIA driver"
        )
    if have is None and kernel is not None:
        return True, (
            f"the NVIDIA kernel driver {kernel} is loaded, but its CUDA library (libcuda.so.1) could not be loaded "
            "(in a container: start it with the NVIDIA Container Toolkit, e.g. --gpus all)"
        )
    if have is not None:
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        hidden = f" (CUDA_VISIBLE_DEVICES={visible!r})" if visible is not None else ""
        return True, f"the NVIDIA driver{named} (CUDA {have[0]}.{have[1]}) reports no usable GPU{hidden}"
    return False, "no NVIDIA GPU driver is loaded on this machine"


def main(argv: list[str] | None = None) -> int:
    """``python -m engine.backend.warp_device``: one JSON line, ``{"cuda_devices", "nvidia_driver", "why"}`` (a
    worker's start-up probe, run in a process of its own so the worker never initialises CUDA before it forks)."""
    import warp as wp

    present, why = cuda_problem()
    sys.stdout.write(json.dumps({"cuda_devices": wp.get_cuda_device_count(), "nvidia_driver": present, "why": why}))
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
