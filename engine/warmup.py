"""Warm a device up before the first job: one small reconstruction and its files, so a worker's first real job does
not pay for the device context, loading Warp's compiled modules (the PNG rows' kernel too) and the pinned host
buffer (measured on the H100 host: a fresh worker's first job took 2.4 s longer than the next ones)."""

from __future__ import annotations

import tempfile
import time
from typing import Any

import numpy as np

WARMUP_SHAPE = (40, 64, 64)  # a bone phantom this size touches every stage (decimation, copies, files) in ~0.3 s


def warm_up(device: str = "auto", max_device_bytes: int | str | None = None) -> dict[str, Any]:
    """Reconstruct a small bone phantom on ``device`` and write its files to a temporary folder (then removed).

    Returns:
        ``{"device": name, "seconds": wall time}``.
    """
    from engine.data.phantom import bone_phantom
    from engine.device import resolve_device
    from engine.io.png_rows import device_rows
    from engine.outputs import write_outputs
    from engine.params import ReconParams
    from engine.pipeline import reconstruct
    from engine.types import Volume

    t0 = time.perf_counter()
    dev = resolve_device(device)
    spec = device if device.startswith("opencl") else str(dev)  # OpenCL: its own context and programs
    hu = bone_phantom(WARMUP_SHAPE, dtype=np.int16) - np.int16(1024)  # the phantom is in HU + 1024
    volume = Volume(hu, (0.5, 0.5, 0.5), units="HU")
    recon = reconstruct(volume, ReconParams(), device=spec, max_device_bytes=max_device_bytes)
    with tempfile.TemporaryDirectory(prefix="bonemesh-warmup-") as out:
        write_outputs(recon, out, device=spec, max_device_bytes=max_device_bytes)
    rows = device_rows(spec)  # a GPU unfilters PNG slices' rows (engine.io.png_rows): its kernel loaded too
    if rows is not None:
        rows.warm_up()
    return {"device": recon.report["device"]["name"], "seconds": time.perf_counter() - t0}
