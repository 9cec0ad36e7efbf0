"""The benchmark phantom as a zip of 16-bit PNG slices (what ``benchmarks.service`` uploads and
``benchmarks.ingest`` loads); numpy, Pillow and the engine's phantom only, so it runs where httpx is absent."""

from __future__ import annotations

import io
import os
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

PHANTOM_SPACING_MM = [0.05, 0.05, 0.05]  # micro-CT-like voxels, as in benchmarks/pipeline.py


def _png(plane: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(plane).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def write_phantom_zip(shape: tuple[int, int, int], path: Path) -> dict[str, Any]:
    """The bone phantom as a zip of 16-bit PNG slices; returns how long it took and the archive's size."""
    from benchmarks.phantom import BONE_LEVEL, bone_phantom

    t0 = time.perf_counter()
    volume = bone_phantom(shape)
    t1 = time.perf_counter()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf, ThreadPoolExecutor(os.cpu_count() or 1) as pool:
        for z, data in enumerate(pool.map(_png, volume)):  # encoded in parallel, written in order
            zf.writestr(f"phantom/phantom_{z:04d}.png", data)
    return {
        "generate_seconds": t1 - t0,
        "encode_seconds": time.perf_counter() - t1,
        "archive_bytes": path.stat().st_size,
        "iso": BONE_LEVEL,
    }
