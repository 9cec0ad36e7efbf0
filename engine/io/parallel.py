"""Slices decoded on a pool of threads (or of the caller's processes), handed back in order.

The codecs the loaders use release the GIL while they inflate and unfilter (Pillow for PNG/JPEG/BMP through
imageio, tifffile's zlib/LZW, zipfile's inflate, the pylibjpeg/OpenJPEG DICOM decoders), so threads decode slices
side by side without copying bytes between processes. :func:`ordered_map` keeps the serial loop's meaning: results
come back in input order, the first failure in that order is the one raised, and at most ``2 * threads`` slices are
read or decoded ahead of the consumer, so memory stays near the output volume's size. ``threads=1`` runs the plain
serial loop on the caller's thread (the reference the parallel path is tested against). The same holds on a
process pool (``engine.io.procs``, for DICOM), with items sent in chunks to save round trips.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor, wait
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

MAX_THREADS = 64  # beyond this, more threads only contend for the archive and the memory bus


def decode_threads(requested: int | None = None) -> int:
    """How many threads decode slices: ``requested`` when given, else the CPUs this process may run on (its
    affinity mask, which ``taskset``, cgroup cpusets and Docker's ``--cpuset-cpus`` set), at most ``MAX_THREADS``.

    Raises:
        ValueError: ``requested`` is not a positive integer.
    """
    if requested is not None:
        if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise ValueError(f"Expected a positive number of decode threads, got {requested!r}")
        return requested
    try:
        available = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        available = os.cpu_count() or 1
    return max(1, min(available, MAX_THREADS))


def ordered_map(
    fn: Callable[[T], R], items: Iterable[T], threads: int, pool: Executor | None = None, chunk: int = 1
) -> Iterator[R]:
    """``map(fn, items)`` on ``threads`` threads (or on ``pool``), yielding results in the order of ``items``.

    Work runs at most ``2 * threads`` items (chunks) ahead of the consumer. An exception from ``fn`` is raised when
    its item's turn comes, as in the serial loop; the items not yet started are then cancelled and the running ones
    waited for, so no thread or process still writes into the caller's arrays once this generator is closed.

    Args:
        fn: called once per item, from a pool thread (from the caller's thread when ``threads == 1`` and no
            ``pool`` is given); with a process pool, a module-level function of picklable items.
        items: the inputs, consumed lazily.
        threads: pool size (the window is twice it); 1 without ``pool`` runs serially.
        pool: an executor of the caller's (``engine.io.procs``), left open; default: a thread pool of our own.
        chunk: items per task (a process pool's round trip costs about 0.1 ms): a chunk's items run in order and
            stop at the first failure, so the failure raised is still the first in the items' order.
    """
    if pool is None and threads <= 1:
        yield from map(fn, items)
        return
    tasks: Iterable[Any] = items
    call: Callable[[Any], Any] = fn
    if chunk > 1:
        tasks, call = _chunks(items, chunk), functools.partial(call_chunk, fn)
    with contextlib.ExitStack() as stack:
        if pool is None:
            pool = stack.enter_context(ThreadPoolExecutor(max_workers=threads, thread_name_prefix="bonemesh-decode"))
        # closed explicitly (cancel, wait) before the pool is left, also when the consumer raises
        results = stack.enter_context(contextlib.closing(_windowed(pool, call, tasks, 2 * max(1, threads))))
        for result in results:
            if chunk <= 1:
                yield result
                continue
            done, error = result
            yield from done
            if error is not None:
                raise error


def call_chunk(fn: Callable[[T], R], items: list[T]) -> tuple[list[R], BaseException | None]:
    """``fn`` over ``items`` in order, up to the first exception: the results before it, and it (or None)."""
    done: list[R] = []
    for item in items:
        try:
            done.append(fn(item))
        except Exception as exc:
            return done, exc
    return done, None


def _chunks(items: Iterable[T], size: int) -> Iterator[list[T]]:
    it = iter(items)
    while batch := list(itertools.islice(it, size)):
        yield batch


def _windowed(pool: Executor, fn: Callable[[T], R], items: Iterable[T], window: int) -> Iterator[R]:
    pending: deque[Future[R]] = deque()
    try:
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= window:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:  # an error (ours or the consumer's) or an early close: stop what has not started, wait for the rest
        for fut in pending:
            fut.cancel()
        wait(pending)
