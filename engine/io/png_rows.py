"""PNG slices unfiltered on the device: the host only inflates, the GPU undoes the row filters.

Decoding a plain grayscale PNG slice on the host is two passes of about equal cost: inflating its zlib stream and
undoing each row's filter (then swapping 16-bit samples to native order). For a 1024 x 1024 16-bit phantom slice
here: 4.3 ms to inflate (libdeflate), 9.1 ms for the whole decode (``engine.io.codecs``). When a job runs on a GPU,
:class:`DeviceRows` keeps the first pass on the host's decode threads, each slice inflated straight into its plane
of a staging array of filtered rows (page-locked for a CUDA device), and gives the second to the device: a slab of
slices at a time, as the slices before it are done, the rows go up, a kernel (``kernels/unfilter.py`` for Warp,
``kernels/unfilter.cl`` for OpenCL) reconstructs them into samples in native order, and the samples come back into
the slices' planes of the volume.

Every slice the device takes is one the host would have given to libpng as a plain grayscale, non-interlaced PNG of
the stack's shape and type whose stream inflates to exactly its rows; anything else (another kind of image, a
damaged stream, a filter type PNG does not define) is decoded on the host as before, with libpng's or Pillow's
error where it is broken. The values are the same either way (tests compare every filter type, 8 and 16 bits).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from engine.backend.base import Backend, Kernel
from engine.io.codecs import inflate_rows
from engine.io.kernels.steps import BLOCK, wavefront_steps

UNFILTER = Kernel(
    "png.unfilter", warp="engine.io.kernels.unfilter:unfilter_kernel", opencl="engine.io.kernels:unfilter.cl:unfilter"
)
SLAB_BYTES = 256 << 20  # filtered rows sent to the device at a time (its memory holds two such slabs per load)

Allocate = Callable[[tuple[int, ...], "np.dtype[Any]"], np.ndarray]


class DeviceRows:
    """One stack's slices, inflated on the host and unfiltered on ``backend`` (a GPU's).

    The loader calls :meth:`start` with the volume it fills, :meth:`take` from its decode threads (slice by slice:
    True where the slice was staged for the device), :meth:`ready` from its own thread as slices finish in order,
    and :meth:`finish` at the end; :meth:`close` (always) waits for the device, so that no copy still reads the
    staging array or writes into the volume once the loader returns or raises.
    """

    def __init__(self, backend: Backend, allocate: Allocate | None = None, slab_bytes: int = SLAB_BYTES) -> None:
        self.backend, self.allocate, self.slab_bytes = backend, allocate, slab_bytes
        self.out: np.ndarray | None = None
        self.rows: np.ndarray | None = None
        self.staged = np.zeros(0, bool)
        self.flushed = 0  # slices before this one have been sent to the device (or needed nothing)
        self.slab = 1  # slices sent at a time (set by start)
        self.pending: list[tuple[int, Any]] = []  # slabs sent: first slice, the device's bad-filter flags

    def start(self, out: np.ndarray, staging: bool = True) -> bool:
        """Stage slices for ``out`` (z, y, x) of uint8 or uint16; False (nothing staged) for any other type. Without
        ``staging`` no staging array is made: the rows come whole slabs at a time (:meth:`send_rows`)."""
        if out.ndim != 3 or out.dtype not in (np.uint8, np.uint16) or not out.flags.c_contiguous:
            return False
        z, h, w = out.shape
        plane = h * (1 + w * out.itemsize)
        shape, dtype = (z, plane), np.dtype(np.uint8)
        rows = None if not staging else np.empty(shape, dtype) if self.allocate is None else self.allocate(shape, dtype)
        self.out, self.rows, self.staged, self.flushed = out, rows, np.zeros(z, bool), 0
        # the kernels index a slab's bytes with 32-bit integers
        self.slab = max(1, min(z, self.slab_bytes // plane, (2**31 - 1) // plane))
        return True

    def take(self, k: int, data: bytes) -> bool:
        """Inflate slice ``k``'s PNG bytes into its rows (on a decode thread); False where the host must decode it."""
        if self.out is None or self.rows is None:
            return False
        self.staged[k] = inflate_rows(data, self.out.shape[1:], self.out.dtype, memoryview(self.rows[k]))
        return bool(self.staged[k])

    def ready(self, done: int) -> None:
        """Slices before ``done`` are decoded or staged: send every whole slab among them to the device."""
        while self.out is not None and self.flushed + self.slab <= done:
            self._send(self.flushed, self.flushed + self.slab)

    def finish(self) -> list[int]:
        """Send what is left, wait for the device; the slices it could not unfilter (a filter type above 4), which
        the host must decode (to report them)."""
        if self.out is None:
            return []
        if self.flushed < len(self.staged):
            self._send(self.flushed, len(self.staged))
        self.backend.synchronize()
        bad = [lo + int(i) for lo, flags in self.pending for i in np.flatnonzero(self.backend.to_host(flags))]
        self.pending.clear()
        return bad

    def close(self) -> None:
        """Wait for the device's copies and let go of the staging array and the volume."""
        if self.pending:
            self.backend.synchronize()
        self.pending.clear()
        self.out = self.rows = None

    def warm_up(self) -> None:
        """Load the kernel (Warp's module, the OpenCL program): one 1 x 1 slice, so a worker's first job does not
        wait for it."""
        be = self.backend
        rows, slices = be.from_host(np.zeros(2, np.uint8)), be.from_host(np.zeros(1, np.int32))
        be.launch(UNFILTER, 1, [rows, 2, slices, be.empty(1, np.uint8), be.zeros(1, np.int32), 1, 1, 1, 0])
        be.synchronize()

    def send_rows(self, lo: int, hi: int, rows: np.ndarray) -> None:
        """Slices ``lo`` to ``hi`` (the next slab, in order) unfiltered from ``rows`` ((hi - lo, rows' bytes),
        inflated elsewhere: ``engine.io.predecode``'s sidecar) into the volume begun by ``start(out,
        staging=False)``; ``rows`` may be written again once the backend has synchronized."""
        self.flushed = hi
        self._unfilter(lo, hi, np.arange(hi - lo, dtype=np.int32), rows)

    def _send(self, lo: int, hi: int) -> None:
        assert self.out is not None and self.rows is not None
        self.flushed = hi
        picked = np.flatnonzero(self.staged[lo:hi]).astype(np.int32)
        if len(picked):
            self._unfilter(lo, hi, picked, self.rows[lo:hi])

    def _unfilter(self, lo: int, hi: int, picked: np.ndarray, host_rows: np.ndarray) -> None:
        """The slab ``lo`` to ``hi``'s slices ``picked`` (indices in the slab) from ``host_rows`` to the device,
        unfiltered there, their samples copied back into the volume."""
        assert self.out is not None
        be, (_, h, w), bpp = self.backend, self.out.shape, self.out.itemsize
        plane = host_rows.shape[1]
        rows = be.from_host(host_rows.reshape(-1))
        slices = be.from_host(picked)
        bad = be.zeros(hi - lo, np.int32)
        samples = be.empty((hi - lo) * h * w * bpp, np.uint8)
        threads = len(picked) * bpp * -(-w // BLOCK)
        for step in range(wavefront_steps(h, w)):  # each step needs the one before: the device's queue orders them
            be.launch(UNFILTER, threads, [rows, plane, slices, samples, bad, h, w, bpp, step])
        dest = self.out[lo:hi].reshape(hi - lo, -1).view(np.uint8)
        # one copy per run of consecutive device slices (the host decoded the others, e.g. the first of the stack)
        firsts = np.flatnonzero(np.diff(picked, prepend=-2) != 1)
        for a, b in zip(firsts, [*firsts[1:], len(picked)], strict=True):
            first, end = int(picked[a]), int(picked[b - 1]) + 1
            be.download(dest[first:end].reshape(-1), samples, src_offset=first * dest.shape[1])
        self.pending.append((lo, bad))  # the device arrays may go: their memory is freed in the queue's order


def device_rows(device: Any) -> DeviceRows | None:
    """A :class:`DeviceRows` for a job on ``device`` (a spec of ``engine.backend.get_backend``) where that is a GPU
    (or another device that is not the host's CPU), staging its rows in the process's page-locked buffer on a CUDA
    device (``engine.staging.pinned_rows``, reused from job to job), else in ``np.empty`` arrays; None on the CPU,
    where libpng's unfiltering on every decode thread is the faster way."""
    from engine.backend.select import get_backend
    from engine.staging import pinned_rows

    backend = get_backend(device)
    return None if backend.is_host else DeviceRows(backend, pinned_rows(device))
