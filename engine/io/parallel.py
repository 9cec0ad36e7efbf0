"""Slices decoded on a pool of threads, handed back in order.

The codecs the loaders use release the GIL while they inflate and unfilter (Pillow for PNG/JPEG/BMP through
imageio, tifffile's zlib/LZW, zipfile's inflate, the pylibjpeg/OpenJPEG DICOM decoders), so threads decode slices
side by side without copying bytes between processes. :func:`ordered_map` keeps the serial loop's meaning: results
come back in input order, the first failure in that order is the one raised, and at most ``2 * threads`` slices are
read or decoded ahead of the consumer, so memory stays near the output volume's size. ``threads=1`` runs the plain
serial loop on the caller's thread (the reference the parallel path is tested against).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

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


def ordered_map(fn: Callable[[T], R], items: Iterable[T], threads: int) -> Iterator[R]:
    """``map(fn, items)`` on ``threads`` threads, yielding results in the order of ``items``.

    Work runs at most ``2 * threads`` items ahead of the consumer. An exception from ``fn`` is raised when its item's
    turn comes, as in the serial loop; the items not yet started are then cancelled and the running ones waited for,
    so no thread still writes into the caller's arrays once this generator is closed.

    Args:
        fn: called once per item, from a pool thread (from the caller's thread when ``threads == 1``).
        items: the inputs, consumed lazily.
        threads: pool size; 1 runs serially without a pool.
    """
    if threads <= 1:
        yield from map(fn, items)
        return
    source = iter(items)
    pending: deque[Future[R]] = deque()
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="bonemesh-decode") as pool:
        try:
            for item in source:
                pending.append(pool.submit(fn, item))
                if len(pending) >= 2 * threads:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:  # an error (ours or the consumer's) or an early close: stop what has not started
            for fut in pending:
                fut.cancel()
