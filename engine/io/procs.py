"""Worker processes for the decoders that hold the GIL (pydicom's parsing), writing into a shared volume.

pydicom parses a file in Python, so threads add little for DICOM (1.29x on 16 cores). :class:`DecodePool` runs
such work in processes instead:

- the workers read the members themselves (``engine.io.readers.read_where``: the zip, tar or file by path), so
  no file bytes cross between processes;
- the volume is one shared memory file (``memfd_create``: anonymous, in RAM, bounded by the memory limit and not
  by the size of ``/dev/shm``, which is 64 MB in a default Docker container), mapped by this process and by each
  worker; a worker decodes a slice straight into its plane and sends back only a few numbers. Memory stays the
  volume plus a slice per worker, as with threads;
- the processes come from a fork server (``forkserver``): a clean process started once per parent (it imports
  the DICOM modules once), from which each worker is forked. Nothing is forked from the caller itself, which may
  hold a CUDA context and other threads (a Celery worker's heartbeat); where there is no fork server, ``spawn``;
- workers die with their parent (``PR_SET_PDEATHSIG``), so a job killed at its hard time limit leaves none behind.

A daemonic process may not start processes (a Celery prefork child is one, unless it drops the flag as
``worker.app`` does), and some sandboxes refuse the semaphores or the fork server: :func:`start_pool` then
returns None and the caller decodes on threads, with the same result.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import multiprocessing as mp
import os
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.reduction import DupFd
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# what the fork server imports once, so each worker forked from it starts with them loaded
PRELOAD = ["__main__", "engine.io.dicom", "pydicom", "pydicom.pixels"]
MAX_CHUNK = 8  # files per task at most
START_TIMEOUT_S = 120.0  # a first worker that has not answered by then: decode on threads instead


def _close_alive_fd(server: Any) -> None:
    """Close this process's copy of the fork server's "alive" pipe end (the server exits only when every holder
    has closed it)."""
    alive = getattr(server, "_forkserver_alive_fd", None)
    if isinstance(alive, int):
        with contextlib.suppress(OSError):
            os.close(alive)
    if server is not None:
        server._forkserver_alive_fd = None


def _forget_fork_server() -> None:
    """In a child made by ``fork``: the parent's fork server is not the child's (it is not the child's child, and it
    serves the parent), and a kept copy of its "alive" pipe end would keep it running after the parent: forget it,
    so the child starts its own when it needs one."""
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    if server is None or getattr(server, "_forkserver_pid", None) is None:
        return
    _close_alive_fd(server)
    server._forkserver_address = server._forkserver_pid = None
    server._lock = threading.Lock()  # another thread of the parent may have held it


os.register_at_fork(after_in_child=_forget_fork_server)  # e.g. a Celery pool child forked after a DICOM load


def unavailable() -> str | None:
    """Why this process cannot use decode processes here (None: it can)."""
    if mp.current_process().daemon:
        return "a daemonic process may not start processes"
    if not hasattr(os, "memfd_create"):
        return "no memfd_create on this platform"
    return None


class DecodePool:
    """Worker processes and the shared memory file they write the volume into (use through :func:`start_pool`).

    Attributes:
        pool: the executor (for ``engine.io.parallel.ordered_map``).
        workers: its size.
    """

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._fd = os.memfd_create("bonemesh-volume", os.MFD_CLOEXEC)
        self._shape: tuple[int, ...] | None = None
        methods = mp.get_all_start_methods()
        ctx = mp.get_context("forkserver" if "forkserver" in methods else "spawn")
        if ctx.get_start_method() == "forkserver":
            ctx.set_forkserver_preload(PRELOAD)  # no effect once this process's fork server runs
        try:
            self.pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(_SharedFd(self._fd),))
        except BaseException:
            os.close(self._fd)
            raise

    def chunk(self, items: int) -> int:
        """Items per task for ``items`` items: a few per round trip, yet at least four tasks per worker."""
        return max(1, min(MAX_CHUNK, items // (4 * self.workers)))

    def shared_array(self, shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray:
        """The volume the workers write into (:func:`worker_array` with the same shape and dtype): zeros, in the
        shared memory file, mapped here. One per pool."""
        if self._shape is not None:
            raise RuntimeError("a DecodePool holds one shared array")
        self._shape = shape
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        os.ftruncate(self._fd, nbytes)
        # allocated and mapped here at once (MAP_POPULATE) rather than a page fault per 4 KiB page in the workers
        # and again here; the workers then only map pages that exist
        flags = mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0)
        buf = mmap.mmap(self._fd, max(nbytes, 1), flags=flags)
        return np.frombuffer(buf, dtype, int(np.prod(shape))).reshape(shape)

    def close(self) -> None:
        """Stop the workers (waiting for running tasks) and close the memory file; arrays mapped here stay valid."""
        try:
            self.pool.shutdown(wait=True, cancel_futures=True)
        finally:
            os.close(self._fd)


@contextlib.contextmanager
def start_pool(workers: int) -> Iterator[DecodePool | None]:
    """A :class:`DecodePool` of ``workers`` processes whose first worker has answered, or None (logged) where
    processes cannot be used here; closed on exit."""
    reason = unavailable()
    dp: DecodePool | None = None
    if reason is None:
        try:
            dp = DecodePool(workers)
            dp.pool.submit(os.getpid).result(timeout=START_TIMEOUT_S)
        except Exception as exc:  # semaphores refused (no /dev/shm), fork server cannot start, worker died...
            reason = f"{type(exc).__name__}: {exc}"
            if dp is not None:
                dp.pool.shutdown(wait=False, cancel_futures=True)
                with contextlib.suppress(OSError):
                    os.close(dp._fd)
                dp = None
    if dp is None:
        log.info("decoding on threads instead of processes: %s", reason)
    try:
        yield dp
    finally:
        if dp is not None:
            dp.close()


class _SharedFd:
    """The memory file's descriptor, passed to each worker as it starts: ``DupFd`` is called while the worker's
    start is pickled, so the fork server (or spawn) hands that worker a duplicate of its own."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self) -> tuple[Any, tuple[Any]]:
        return _detach, (DupFd(self.fd),)


def _detach(dup: Any) -> int:
    return int(dup.detach())


# ---- in the worker processes ------------------------------------------------------------------------------------

_FD: int | None = None
_VIEW: tuple[int, mmap.mmap] | None = None


def _init(fd: int) -> None:
    """Worker start: take the memory file, die with the parent, no warnings (pydicom's about legacy headers)."""
    global _FD
    _FD = fd
    warnings.simplefilter("ignore")
    # the fork server hands each child the parent's "alive" pipe end, and exits only when every holder has closed
    # it: a worker that kept it would keep the server, and so itself, alive after the parent's death
    from multiprocessing import forkserver

    _close_alive_fd(getattr(forkserver, "_forkserver", None))
    if sys.platform == "linux":
        with contextlib.suppress(Exception):
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the parent, which stops the pool


def worker_array(shape: tuple[int, ...], dtype: np.dtype[Any] | str) -> np.ndarray:
    """In a worker: the pool's shared array (as :meth:`DecodePool.shared_array` made it), mapped once."""
    global _VIEW
    if _FD is None:
        raise RuntimeError("not in a DecodePool worker")
    count = int(np.prod(shape))
    nbytes = count * np.dtype(dtype).itemsize
    if _VIEW is None or _VIEW[0] != nbytes:
        _VIEW = (nbytes, mmap.mmap(_FD, max(nbytes, 1)))
    return np.frombuffer(_VIEW[1], dtype, count).reshape(shape)
