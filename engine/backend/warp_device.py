"""Warp's runtime and devices, below the backend choice (``engine.backend.select``) and the device specs
(``engine.device``): ``init_runtime`` (Warp initialised quietly, once), ``cuda_available`` and ``warp_device`` (a
concrete ``"cpu"`` / ``"cuda"`` / ``"cuda:N"`` spec to a ``wp.Device``). Imports nothing of the engine, so the
modules above it import it without a cycle."""

from __future__ import annotations

import os
from typing import Any

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
            raise ValueError(f"Expected an available CUDA device ({n} present), got {spec!r}")
        return wp.get_device(f"cuda:{index}")
    return wp.get_device("cpu")
