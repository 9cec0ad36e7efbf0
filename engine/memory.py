"""The device memory budget (``max_device_bytes``): the cost model the stages plan with, and the peak measured.

Every stage of ``engine.pipeline.reconstruct`` and ``engine.outputs.write_outputs`` plans its device allocations
against one budget in bytes. The model below is what they plan with; the peak actually used is measured from the
device's memory pool (CUDA: the pool's used-memory high-water mark, reset at the start of a job) or, on the CPU,
by Warp's allocation tracker, and reported beside the budget.
"""

from __future__ import annotations

import ctypes
import re
from typing import Any

# Planning figures, per face of a triangle mesh with about half as many vertices as faces (measured on the H100:
# docs/benchmarks.md, "Any scan size in a fixed memory budget").
MESH_BYTES_PER_FACE = 18  # positions (12 B per vertex) and faces (12 B)
DECIMATE_BYTES_PER_FACE = 300  # the mesh, its copy, stars, classes, quadrics, per-edge keys and positions
# islands, smoothing, normals and the model's checks: the mesh, its stars (18 B), smoothing's moved copy and flags
# or the compacted copy of islands (measured on the H100 and the CPU: at most 46 B per face, docs/benchmarks.md)
FINISH_BYTES_PER_FACE = 52
# speck removal on a mesh already on the device: its pieces' labels and measures, a copy of its faces and their
# compaction (measured on the H100: 33 B per face beyond the mesh)
ISLANDS_BYTES_PER_FACE = 40
STATS_CHUNK_FACES = 1 << 22  # the model's checks measure its faces this many at a time (20 B each)
# write_outputs: the mesh and its normals (24 B), the faces rewound (12 B), the patient, viewing and glTF copies of
# positions and normals (30 B); the STL facets (48 B a face) go to the host LAYOUT_CHUNK_FACES at a time
LAYOUT_BYTES_PER_FACE = 72
LAYOUT_CHUNK_FACES = 1 << 20
SLAB_SHARE = 0.25  # of the budget, for one slab of the volume stages when the whole mesh is kept (undecimated)
# or this share when the mesh is decimated in groups of slabs: besides a slab, only the groups decimated so far
# (``engine.stages.stream.SPILL_SHARE``, then they go to the host) and the slabs' meshes not yet decimated (a few %)
STREAM_SLAB_SHARE = 0.5

_UNITS = {"": 1, "b": 1, "k": 1 << 10, "kb": 1000, "kib": 1 << 10, "m": 1 << 20, "mb": 10**6, "mib": 1 << 20}
_UNITS |= {"g": 1 << 30, "gb": 10**9, "gib": 1 << 30, "t": 1 << 40, "tb": 10**12, "tib": 1 << 40}


def parse_bytes(text: str | int | None) -> int | None:
    """``"8GiB"``, ``"512 MiB"``, ``"2G"`` (binary) or a plain byte count; ``None``, ``""`` or ``"0"``: no budget."""
    if text is None or isinstance(text, int):
        if isinstance(text, int) and text < 0:
            raise ValueError(f"a memory budget must be positive, got {text}")
        return text or None
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
    if not m or m.group(2).lower() not in _UNITS:
        raise ValueError(f"a memory budget is a byte count with an optional unit (e.g. 8GiB, 512MiB), got {text!r}")
    value = int(float(m.group(1)) * _UNITS[m.group(2).lower()])
    return value or None


def host_fallback(device: Any) -> Any:
    """Where the stages go that cannot fit a GPU's budget (the finished model's islands, smoothing, normals and file
    layout): Warp's CPU device, outside the budget. ``None`` for the CPU device itself, whose memory the budget is:
    there a model over the budget stays an error."""
    import warp as wp

    return wp.get_device("cpu") if device.is_cuda else None


def place(device: Any, need: int, budget: int | None, what: str, remedy: str = "") -> tuple[Any, dict | None]:
    """Where work that needs ``need`` bytes of device memory runs: ``(device, None)`` within the budget; past it
    ``(host, note)``, the host of ``host_fallback`` with a note for the report (``device``, ``reason``); on the CPU
    device a ``BudgetError`` naming the budget that works (``what``: the work, ``remedy``: another way out)."""
    from engine.errors import BudgetError

    if budget is None or need <= budget:
        return device, None
    reason = f"{what} needs about {mib(need)} of device memory, over the budget of {mib(budget)}"
    host = host_fallback(device)
    if host is None:
        raise BudgetError(f"{reason}: give at least {mib(need)}{remedy}", needed=need)
    return host, {"device": str(host), "reason": reason}


def finish_bytes(n_faces: int) -> int:
    """Device bytes the finishing stages of an ``n_faces`` model need (``FINISH_BYTES_PER_FACE`` and the checks'
    chunk of face measures)."""
    return n_faces * FINISH_BYTES_PER_FACE + min(n_faces, STATS_CHUNK_FACES) * 20


def layout_bytes(n_faces: int) -> int:
    """Device bytes of laying out an ``n_faces`` model for its files (``engine.outputs.lay_out``)."""
    return n_faces * LAYOUT_BYTES_PER_FACE + min(n_faces, LAYOUT_CHUNK_FACES) * 48


def mib(n: int) -> str:
    return f"{n / 2**20:,.0f} MiB"


class PeakMemory:
    """The most device memory a job had in use between ``start()`` and ``peak()``, beyond what was in use before.

    CUDA: the memory pool's used-memory high-water mark (reset through the driver at ``start``; where the reset is
    not available, the process's mark, labelled ``since process start``) minus the memory in use at ``start``
    (``baseline``: e.g. a finished job's mesh still held). CPU: Warp's allocation tracker (new allocations only).
    """

    def __init__(self, device: Any) -> None:
        self.device = device
        self.how = "none"
        self.baseline = 0  # device memory already in use at ``start`` (not the job's): subtracted from the peak
        self._tracker: Any = None

    def start(self) -> PeakMemory:
        import warp as wp

        if self.device.is_cuda and self.device.is_mempool_enabled:
            wp.synchronize_device(self.device)
            self.baseline = int(wp.get_mempool_used_mem_current(self.device))
            self.how = "cuda memory pool high-water mark" if _reset_pool_high(self.device) else "since process start"
        elif not self.device.is_cuda:
            self._tracker = wp.ScopedMemoryTracker("bonemesh", print=False)
            self._tracker.__enter__()
            self._tracker.clear()
            self.how = "warp allocation tracker"
        return self

    def peak(self) -> int | None:
        import warp as wp

        if self.device.is_cuda and self.device.is_mempool_enabled:
            wp.synchronize_device(self.device)
            return int(wp.get_mempool_used_mem_high(self.device)) - self.baseline
        if self._tracker is not None:
            text: list[str] = []
            self._tracker.report_func = text.append
            self._tracker.report(max_items=0)
            m = re.search(r"Peak usage:\s*\n\s*cpu\s+([0-9.]+)\s*(\w+)", "".join(text))
            if m:  # the tracker's "MB" and "GB" are binary
                scale = {"b": 1, "bytes": 1, "kb": 1 << 10, "mb": 1 << 20, "gb": 1 << 30, "tb": 1 << 40}
                return int(float(m.group(1)) * scale.get(m.group(2).lower(), 1))
        return None

    def stop(self) -> None:
        if self._tracker is not None:
            self._tracker.__exit__(None, None, None)
            self._tracker = None


def _reset_pool_high(device: Any) -> bool:
    """Reset the device's default memory pool's used-memory high-water mark (CUDA driver API)."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
        dev = ctypes.c_int()
        pool = ctypes.c_void_p()
        if cuda.cuDeviceGet(ctypes.byref(dev), int(device.ordinal)) != 0:
            return False
        if cuda.cuDeviceGetDefaultMemPool(ctypes.byref(pool), dev) != 0:
            return False
        zero = ctypes.c_uint64(0)
        used_mem_high = 8  # CU_MEMPOOL_ATTR_USED_MEM_HIGH
        return cuda.cuMemPoolSetAttribute(pool, used_mem_high, ctypes.byref(zero)) == 0
    except (OSError, AttributeError):
        return False
