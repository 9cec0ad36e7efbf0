"""Warm a device up before the first job: one small reconstruction and its files, so a worker's first real job does
not pay for the device context and loading Warp's compiled modules (the PNG rows' kernel too); on a CUDA device, the
page-locked buffers a load fills are allocated too, for a volume of the size asked (``BONEMESH_WARMUP_VOLUME_BYTES``).

Measured: on the H100 host a fresh worker's first job took 2.4 s longer than the next ones before any warm-up; with
the small reconstruction alone, its load still took 1.2-2.1 s against 0.45 s, page-locking 2 GB of buffers for the
476 x 1024 x 1024 phantom (``benchmarks/results/throughput_cuda_2xh100_24jobs_unfilter_device_*.json``). On this
2-core CPU the warm-up takes 1.3 s and a CPU worker's first job was 1.5 s slower without it."""

from __future__ import annotations

import tempfile
import time
from typing import Any

import numpy as np

WARMUP_SHAPE = (40, 64, 64)  # a bone phantom this size touches every stage (decimation, copies, files) in ~0.3 s


def warm_up(
    device: Any = "auto",
    max_device_bytes: int | str | None = None,
    volume_bytes: int = 0,
    png_rows: bool = True,
) -> dict[str, Any]:
    """Reconstruct a small bone phantom on ``device`` (a spec, or a resolved ``engine.job.Runtime``: its backend,
    budget and PNG decoder, exactly what its jobs use) and write its files to a temporary folder (then removed); on
    a CUDA device, allocate the load's page-locked buffers for a volume of ``volume_bytes`` (the filtered rows' too
    where ``png_rows``: PNG slices are unfiltered on the device, ``engine.io.png_rows``).

    Returns:
        ``{"device": name, "seconds": wall time, "pinned_bytes": page-locked bytes held for loads}``.
    """
    from engine.data.phantom import bone_phantom
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct
    from engine.job.runtime import Runtime, resolve_runtime
    from engine.params import ReconParams
    from engine.staging import reserve_load_buffers
    from engine.types import Volume

    t0 = time.perf_counter()
    runtime = device if isinstance(device, Runtime) else resolve_runtime(device, max_device_bytes)
    backend, budget = runtime.backend, runtime.budget
    hu = bone_phantom(WARMUP_SHAPE, dtype=np.int16) - np.int16(1024)  # the phantom is in HU + 1024
    volume = Volume(hu, (0.5, 0.5, 0.5), units="HU")
    recon = reconstruct(volume, ReconParams(), device=runtime.device, max_device_bytes=budget)  # every device
    with tempfile.TemporaryDirectory(prefix="bonemesh-warmup-") as out:
        write_outputs(recon, out, device=backend, max_device_bytes=budget)
    rows = runtime.rows() if png_rows else None  # a GPU unfilters PNG slices' rows: its kernel loaded too
    if rows is not None:
        rows.warm_up()
    pinned = reserve_load_buffers(backend, volume_bytes, rows=rows is not None)
    return {"device": recon.report["device"]["name"], "seconds": time.perf_counter() - t0, "pinned_bytes": pinned}
