"""Uploads of z planes of a host volume to the device for the streamed volume stages
(``engine.isosurface.stream``): through a ring of page-locked host planes that a thread fills ahead
(``PlaneFeed``), or copied directly (``DirectFeed``). The ring is the process's, held by one job at a time
(``engine.staging.PinnedBuffer``).

The volume is a host array, or a scan read slab by slab from disk (``engine.io.slabs.SlabSource``, a job under a
host memory bound): its planes are then decoded straight into the ring, or into the device array on Warp's CPU
device, or at most ``read_bytes`` at a time into a host array that is copied up and dropped.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import numpy as np

from engine.staging import PinnedBuffer, pinned_max

FEED_MIN_BYTES = 256 << 20  # the pinned ring of planes that the slab uploads go through: at least this,
RING_SLABS = 2  # or this many of the largest slabs (the next slab is read while the device works on this one),
FEED_MAX_BYTES = 2 << 30  # up to this (locking 1 GiB took 0.6 s on the H100 host, once per process; 2 GiB holds
# two slabs of 1024 x 1024 uint16 planes in an 8 GiB budget: the 8 G voxel phantom on an H200 waited 0.16 s for planes
# in all, against 0.49 s with 1 GiB, docs/multi-gpu.md)
FEED_CHUNK_BYTES = 32 << 20  # the ring is filled this much at a time,
READERS = 4  # by this many threads (one copied 5 GB/s on the H100 host: slower than the pageable upload)


def _planes(volume: Any, z0: int, z1: int) -> np.ndarray:
    """Planes ``z0..z1 - 1`` of a host array (a view) or of a ``SlabSource`` (read)."""
    return volume[z0:z1] if isinstance(volume, np.ndarray) else volume.read(z0, z1)


def upload_planes(volume: Any, zlo: int, zhi: int, device: Any, read_bytes: int | None = None) -> Any:
    """Planes ``zlo..zhi`` of a host volume (or a ``SlabSource``) as a new array on ``device`` (a Warp device, or a
    backend of ``engine.backend``), copied directly (pageable); a source's planes are read at most ``read_bytes`` at
    a time (at least a plane) where the device is Warp's."""
    if hasattr(device, "from_host"):  # a backend (OpenCL: its queue does the copy)
        return device.from_host(np.ascontiguousarray(_planes(volume, zlo, zhi + 1)))
    import warp as wp

    if isinstance(volume, np.ndarray):
        return wp.array(np.ascontiguousarray(volume[zlo : zhi + 1]), device=device)
    ny, nx = volume.shape[1:]
    out = wp.empty((zhi - zlo + 1, ny, nx), dtype=wp.dtype_from_numpy(volume.dtype), device=device)
    if not device.is_cuda:  # the device's memory is the host's: decoded in place
        volume.read_into(zlo, zhi + 1, out.numpy())
        return out
    step = max(1, (read_bytes or volume.nbytes) // max(volume.plane_bytes, 1))
    plane = ny * nx
    for z in range(zlo, zhi + 1, step):
        host = volume.read(z, min(z + step, zhi + 1))
        wp.copy(out, wp.array(host, device="cpu", copy=False), dest_offset=(z - zlo) * plane, count=host.size)
        wp.synchronize_device(device)  # the host slab is dropped next
    return out


class DirectFeed:
    """``PlaneFeed``'s interface without the ring: every request copied directly (``upload_planes``)."""

    stats = None

    def __init__(self, volume: Any, device: Any, read_bytes: int | None = None) -> None:
        self.volume, self.device, self.read_bytes = volume, device, read_bytes

    def upload(self, zlo: int, zhi: int) -> Any:
        return upload_planes(self.volume, zlo, zhi, self.device, self.read_bytes)


class PlaneFeed:
    """Uploads z planes of a host volume to a device in the order a slab pass asks for them, through a ring of
    page-locked host planes (``ring``) that a thread fills ahead from the volume.

    A slab pass asks for planes going forward in z: each request ``upload(zlo, zhi)`` starts at or after the start
    of the one before (a slab redone smaller starts where it did, the next slab just before the last one ended), so
    the planes before a request's start are released to the thread, which refills their slots with the planes ahead
    while the device works on the slab (Gaussian, MC33, a group's decimation). The copy from the ring to the device
    is asynchronous at the link's speed; without the ring, each slab's copy from the volume's pageable memory held
    the host and the device for its whole length (measured on the H100 host for 100 MB: 10.8 ms pageable, 1.9 ms
    pinned). A request behind the released planes (a slab redone smaller after one longer than the ring) is copied
    directly, the same values.
    """

    def __init__(self, volume: Any, device: Any, ring: Any, ring_bytes: int) -> None:
        import warp as wp

        self.volume, self.device = volume, device
        nz, ny, nx = volume.shape
        self.plane = ny * nx
        self.wp_dtype = wp.dtype_from_numpy(volume.dtype)
        self.cap = min(min(ring_bytes, ring.capacity) // (self.plane * volume.itemsize), nz)
        self.ring = wp.array(ptr=ring.ptr, dtype=self.wp_dtype, shape=(self.cap, ny, nx), device="cpu")
        self.view = self.ring.numpy()
        self.events: list[Any] = [None] * self.cap  # the last copy that read each slot
        self.chunk = max(1, min(FEED_CHUNK_BYTES // (self.plane * volume.itemsize), self.cap))
        self.filled = 0  # planes [0, filled) are (or were) in the ring
        self.low = 0  # planes before this are released
        self.error: BaseException | None = None
        self.stopped = False
        self.stats = {"requests": 0, "direct": 0, "longest_request_planes": 0, "waited_seconds": 0.0}
        self.stats |= {"first_wait_seconds": 0.0, "read_seconds": 0.0, "ring_wait_seconds": 0.0}
        self.cond = threading.Condition()
        self.readers = ThreadPoolExecutor(READERS, thread_name_prefix="bonemesh-plane-read")
        self.thread = threading.Thread(target=self._fill, name="bonemesh-plane-feed", daemon=True)
        self.thread.start()

    def _fill(self) -> None:
        import warp as wp

        nz = self.volume.shape[0]
        try:
            while True:
                with self.cond:
                    while not self.stopped and (self.filled >= nz or self.filled >= self.low + self.cap):
                        self.cond.wait()
                    if self.stopped:
                        return
                    z = max(self.filled, self.low)  # (planes a request skipped are not read)
                    s = z % self.cap
                    n = min(nz, self.low + self.cap) - z
                    n = min(n, self.cap - s, self.chunk)
                    waits = {id(e): e for e in self.events[s : s + n] if e is not None}
                t0 = time.perf_counter()
                for ev in waits.values():  # the slots' last copies to the device have been read
                    wp.synchronize_event(ev)
                t1 = time.perf_counter()
                if isinstance(self.volume, np.ndarray):
                    self._read(self.view[s : s + n].reshape(-1), self.volume[z : z + n].reshape(-1))
                else:  # a scan read slab by slab: decoded straight into the ring
                    self.volume.read_into(z, z + n, self.view[s : s + n])
                self.stats["ring_wait_seconds"] += t1 - t0
                self.stats["read_seconds"] += time.perf_counter() - t1
                with self.cond:
                    self.events[s : s + n] = [None] * n
                    self.filled = z + n
                    self.cond.notify_all()
        except BaseException as exc:  # handed to the next request
            with self.cond:
                self.error = exc
                self.cond.notify_all()

    def _read(self, dst: np.ndarray, src: np.ndarray) -> None:
        """``dst[:] = src`` in ``READERS`` parts at once (``np.copyto`` releases the GIL)."""
        cuts = np.linspace(0, len(src), READERS + 1).astype(np.int64)
        parts = [(a, b) for a, b in itertools.pairwise(cuts) if b > a]
        list(self.readers.map(lambda ab: np.copyto(dst[ab[0] : ab[1]], src[ab[0] : ab[1]]), parts))

    def upload(self, zlo: int, zhi: int) -> Any:
        """Planes ``zlo..zhi`` as a new array on the device (``wp.array(volume[zlo:zhi + 1])``)."""
        import warp as wp

        self.stats["requests"] += 1
        self.stats["longest_request_planes"] = max(self.stats["longest_request_planes"], zhi - zlo + 1)
        with self.cond:
            behind = zlo < self.low
            if not behind:
                self.low = zlo
                self.cond.notify_all()
        if behind:
            self.stats["direct"] += 1
            return upload_planes(self.volume, zlo, zhi, self.device, self.cap * self.plane * self.volume.itemsize)
        ny, nx = self.volume.shape[1:]
        out = wp.empty((zhi - zlo + 1, ny, nx), dtype=self.wp_dtype, device=self.device)
        stream = wp.get_stream(self.device) if self.device.is_cuda else None
        z = zlo
        while z <= zhi:
            with self.cond:
                if z >= self.low + self.cap:  # a request longer than the ring: its first planes are released
                    self.low = z - self.cap + 1
                    self.cond.notify_all()
                t0 = time.perf_counter()
                while self.filled <= z and self.error is None:
                    self.cond.wait()
                waited = time.perf_counter() - t0
                self.stats["waited_seconds"] += waited
                if self.stats["requests"] == 1:  # the first slab's planes: read before the device has work
                    self.stats["first_wait_seconds"] += waited
                if self.error is not None:
                    raise RuntimeError(f"reading the volume's planes failed: {self.error}") from self.error
                s = z % self.cap
                n = min(zhi + 1, self.filled, z + self.cap - s) - z
            wp.copy(out, self.ring, dest_offset=(z - zlo) * self.plane, src_offset=s * self.plane, count=n * self.plane)
            if stream is not None:
                ev = stream.record_event()
                with self.cond:
                    self.events[s : s + n] = [ev] * n
            z += n
        return out

    def close(self) -> None:
        import warp as wp

        with self.cond:
            self.stopped = True
            self.cond.notify_all()
        self.thread.join()
        self.readers.shutdown()
        if self.device.is_cuda:
            wp.synchronize_device(self.device)  # no copy still reads the ring when the next job takes it


_FEED = PinnedBuffer()


@contextmanager
def plane_feed(
    volume: Any,
    device: Any,
    slab_bytes: int = 0,
    *,
    force: bool = False,
    ring_bytes: int | None = None,
    host_bytes: int | None = None,
    pinned: PinnedBuffer | None = None,
) -> Iterator[Any]:
    """A feed whose ``upload(zlo, zhi)`` gives planes zlo..zhi of ``volume`` (a host array, or a scan read slab by
    slab: ``engine.io.slabs.SlabSource``) as a new array on ``device``. For a CUDA device (with ``force``, any
    device: for tests) a ``PlaneFeed`` on the process's pinned ring, sized for ``RING_SLABS`` slabs of up to
    ``slab_bytes`` (at least ``FEED_MIN_BYTES``, at most ``FEED_MAX_BYTES`` and ``BONEMESH_PINNED_MAX``), or
    ``ring_bytes`` exactly on any device (``Budget.feed_ring_bytes``: for tests), and grown when a larger one is
    needed; where the ring is held by another job, would hold fewer than two planes or cannot be locked, a
    ``DirectFeed``. ``host_bytes``: the most host memory the ring (or a direct feed's reads of a source) may take
    (``Budget.host_read_bytes``, under a host memory bound). ``pinned``: the ring to use instead of the process's
    (a job over several devices gives each part its own: ``engine.isosurface.multi``)."""
    if isinstance(volume, np.ndarray):
        volume = np.ascontiguousarray(volume)
    if getattr(device, "kind", None) == "opencl":  # the pinned ring is Warp's: an OpenCL queue copies directly
        yield DirectFeed(volume, device, host_bytes)
        return
    import warp as wp

    dev = wp.get_device(getattr(device, "device", device))
    plane_bytes = volume.shape[1] * volume.shape[2] * volume.itemsize if volume.size else 0
    if ring_bytes is None:
        ring_bytes = min(max(FEED_MIN_BYTES, RING_SLABS * slab_bytes), FEED_MAX_BYTES, pinned_max(), volume.nbytes)
        if host_bytes is not None:
            ring_bytes = min(ring_bytes, host_bytes)
    else:
        force = True
    usable = (dev.is_cuda or force) and volume.size and 2 * plane_bytes <= ring_bytes
    buffer = _FEED if pinned is None else pinned
    if not usable or not buffer.lock.acquire(blocking=False):
        yield DirectFeed(volume, dev, host_bytes)
        return
    feed = None
    try:
        try:
            ring = buffer.at_least(ring_bytes, ring_bytes, pinned=dev.is_cuda)
        except (RuntimeError, MemoryError):  # the host would not lock that much memory: copy directly
            ring = None
        if ring is None:
            yield DirectFeed(volume, dev)
            return
        feed = PlaneFeed(volume, dev, ring, ring_bytes)
        yield feed
    finally:
        if feed is not None:
            feed.close()
        buffer.lock.release()
