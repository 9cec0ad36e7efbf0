"""What an isosurface run did (``IsosurfaceStats``) and its per-stage timer (``Timer``): shared by the slab pass
(``engine.isosurface.slabs``) and its wrappers (``engine.isosurface.mc33``, ``engine.isosurface.stream``)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class IsosurfaceStats:
    """What a run did: slabs, active blocks, table misses (must be 0); per-stage times when ``profile``."""

    profile: bool = False
    timings: dict[str, float] = field(default_factory=dict)
    level_in_range: bool = False
    slabs: int = 0
    blocks: int = 0
    active_blocks: int = 0
    table_misses: int = 0
    peak_slab_bytes: int = 0
    retries: int = 0
    slab_layers: list[int] = field(default_factory=list)


class Timer:
    """Per-stage wall times, synchronising the device only when profiling (``stats.profile``)."""

    def __init__(self, st: IsosurfaceStats, dev: Any) -> None:
        """``dev``: an ``engine.backend.Backend`` or a Warp device."""
        self.st, self.dev = st, dev
        self.t = time.perf_counter()

    def lap(self, name: str) -> None:
        if not self.st.profile:
            return
        from engine.backend.select import get_backend

        get_backend(self.dev).synchronize()  # sync point (profiling only)
        now = time.perf_counter()
        self.st.timings[name] = self.st.timings.get(name, 0.0) + now - self.t
        self.t = now
