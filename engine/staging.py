"""Page-locked host memory for the copies from a CUDA device to the host (the finished model's file buffers).

A copy into page-locked ("pinned") memory runs at the link's speed; a copy into a fresh numpy array first pays for
the array's pages as they are touched. Measured on the H100 host for 443 MB (a 6.2 M-face model's STL facets and
glTF buffers): 0.38 s into fresh numpy arrays, 29 ms into numpy memory already touched, 8.5 ms into pinned memory.
Allocating the pinned buffer costs about 0.2 s for that size, so it is allocated once per process and reused by
every job (a worker runs one job after another), grown when a larger model comes, up to ``BONEMESH_PINNED_MAX``
(default 4 GiB). One job at a time holds it: another at the same time, a model over the cap, or a device that is
not CUDA gets ordinary arrays, the same values.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from engine.budget import parse_bytes

ALIGN = 256
DEFAULT_MAX = 4 << 30


def pinned_max() -> int:
    return parse_bytes(os.environ.get("BONEMESH_PINNED_MAX")) or DEFAULT_MAX


def pinned_bytes(nbytes: int, *, pinned: bool = True) -> Any:
    """A Warp CPU array of at least ``nbytes`` bytes, page-locked (``pinned``), in 8-byte elements (an array of
    bytes stops at 2 GiB: Warp's dimensions are 32-bit)."""
    import warp as wp

    return wp.empty(-(-nbytes // 8), dtype=wp.int64, device="cpu", pinned=pinned)


class HostCopies:
    """Copies device arrays to the host: into the pinned buffer (``buf``, a Warp CPU array) where one is held,
    else as ordinary numpy arrays. The arrays it returns are valid until the ``host_copies`` block ends; read them
    only after ``wait()``."""

    def __init__(self, buf: Any, device: Any) -> None:
        self.buf, self.device, self.used = buf, device, 0
        self.pinned = buf is not None

    def __call__(self, arr: Any) -> np.ndarray:
        import warp as wp

        if self.buf is None:
            copy: np.ndarray = arr.numpy()
            return copy
        dest, view = self.empty(arr.shape, arr.dtype)
        wp.copy(dest, arr)
        return view

    def empty(self, shape: tuple[int, ...], dtype: Any) -> tuple[Any, np.ndarray]:
        """A host array to fill piece by piece (``wp.copy`` into its row slices): ``(warp CPU array, numpy view)``,
        in the pinned buffer where one is held."""
        import warp as wp

        if self.buf is None:
            dest = wp.empty(shape, dtype=dtype, device="cpu")
            return dest, dest.numpy()
        nbytes = int(np.prod(shape)) * wp.types.type_size_in_bytes(dtype)
        if self.used + nbytes > self.buf.capacity:
            raise ValueError("host copies past the size they were planned for")
        dest = wp.array(ptr=self.buf.ptr + self.used, dtype=dtype, shape=shape, device="cpu")
        self.used += -(-nbytes // ALIGN) * ALIGN
        return dest, dest.numpy()

    def wait(self) -> None:
        import warp as wp

        wp.synchronize_device(self.device)  # pinned or pageable, the copies have landed


class PinnedBuffer:
    """A process-wide host buffer, held by one job at a time (``lock``), kept for the next and grown on demand."""

    def __init__(self) -> None:
        self.buf: Any = None
        self.lock = threading.Lock()

    def at_least(self, nbytes: int, size: int, pinned: bool = True) -> Any:
        """The buffer, reallocated (``size`` bytes, the old one freed first) where it holds fewer than ``nbytes`` or
        is not ``pinned`` as asked."""
        if self.buf is None or self.buf.capacity < nbytes or self.buf.pinned != pinned:
            self.buf = None
            self.buf = pinned_bytes(size, pinned=pinned)
        return self.buf


_PINNED = PinnedBuffer()


@contextmanager
def host_copies(device: Any, nbytes: int) -> Iterator[HostCopies]:
    """A ``HostCopies`` for up to ``nbytes`` (each array rounded up to 256 bytes) from ``device``: through the
    process's pinned buffer where it can be had, else plain."""
    import warp as wp

    dev = wp.get_device(device)
    if not dev.is_cuda or nbytes > pinned_max() or not _PINNED.lock.acquire(blocking=False):
        yield HostCopies(None, dev)
        return
    try:
        size = min(max(nbytes, 64 << 20) * 5 // 4, max(pinned_max(), nbytes))
        yield HostCopies(_PINNED.at_least(nbytes, size), dev)
    finally:
        _PINNED.lock.release()


class VolumeBuffer(PinnedBuffer):
    """The process's buffer for loaded volumes (``engine.io.load_volume``'s ``allocate``): a ``PinnedBuffer``
    (page-locked where ``pinned``) kept from job to job and grown on demand, up to ``BONEMESH_PINNED_MAX``.

    A volume decoded into page-locked memory goes to a CUDA device at the link's speed, and its pages are touched
    once per process instead of once per job. Measured on the 2 x H100 host for a 476 x 1024 x 1024 uint16 volume
    (1 GB): the upload took 0.11-0.16 s from a fresh numpy array (docs/benchmarks.md), and a load into memory already
    touched spent 0.13 s of system time against 0.30 s (``benchmarks/results/loadprobe_2xh100.json``).

    It is handed out only while nothing holds the previous volume: each call views the buffer through a new numpy
    array, and any array or view still alive from an earlier call holds the buffer (its reference count says so);
    then, or past the cap, the call returns a plain ``np.empty``, the same values either way.
    """

    def __init__(self, pinned: bool = True) -> None:
        super().__init__()
        self.pinned = pinned

    def __call__(self, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        dtype = np.dtype(dtype)
        nbytes = int(np.prod(shape)) * dtype.itemsize
        with self.lock:
            if not self._free(nbytes):
                return np.empty(shape, dtype)
            whole: np.ndarray = self._grown(nbytes).numpy()
            out: np.ndarray = whole.view(np.uint8)[:nbytes].view(dtype).reshape(shape)
            return out

    def reserve(self, nbytes: int) -> int:
        """Grow the buffer now for arrays up to ``nbytes`` (a worker's warm-up), not during the first job that needs
        it; nothing where nothing may be handed out (held, past the cap, 0). Returns the buffer's bytes."""
        with self.lock:
            if self._free(nbytes):
                self._grown(nbytes)
            return 0 if self.buf is None else int(self.buf.capacity)

    def _free(self, nbytes: int) -> bool:
        return 0 < nbytes <= pinned_max() and not (self.buf is not None and self._held())

    def _grown(self, nbytes: int) -> Any:
        return self.at_least(nbytes, min(nbytes * 9 // 8, pinned_max()), self.pinned)

    def _held(self) -> bool:
        """Whether an array handed out earlier still lives (it, or a view of it, holds ``buf``)."""
        return sys.getrefcount(self.buf) > 2  # the attribute and getrefcount's argument


_VOLUMES = VolumeBuffer(pinned=True)  # allocated at its first use
_ROWS = VolumeBuffer(pinned=True)  # PNG slices' filtered rows on their way to the device (engine.io.png_rows)


def pinned_volumes(device: Any) -> VolumeBuffer | None:
    """The process's page-locked ``VolumeBuffer`` for loaded volumes where ``device`` (a spec of
    ``engine.device.resolve_device``) resolves to a CUDA device, else None (plain ``np.empty``)."""
    return _on_cuda(_VOLUMES, device)


def pinned_rows(device: Any) -> VolumeBuffer | None:
    """The same for PNG slices' filtered rows on their way to ``device`` (``engine.io.png_rows.device_rows``)."""
    return _on_cuda(_ROWS, device)


def reserve_load_buffers(device: Any, volume_bytes: int, rows: bool) -> int:
    """Allocate the page-locked buffers a load onto ``device`` (a CUDA device; elsewhere nothing) uses, for a volume
    of ``volume_bytes``: the volume's, and where ``rows`` (PNG slices unfiltered on the device) the filtered rows'
    (the rows of a volume of B bytes are B plus one filter byte per row, inside the 1/8 the buffer adds). Page-locking
    a gigabyte takes a few tenths of a second, which a worker's warm-up pays instead of its first job. Returns the
    bytes held."""
    buffers = [pinned_volumes(device), pinned_rows(device) if rows else None]
    return sum(b.reserve(volume_bytes) for b in buffers if b is not None)


def _on_cuda(buffer: VolumeBuffer, device: Any) -> VolumeBuffer | None:
    from engine.device import resolve_device

    return buffer if resolve_device(device).is_cuda else None
