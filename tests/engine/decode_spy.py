"""A load with DICOM decoding in processes asked for, which also tells whether a process pool really ran: the test
children (spawned, forked, billiard) call it to see which way ``engine.io.procs`` went there."""

from __future__ import annotations

from engine.types import Volume


def load_counting_pools(path: str) -> tuple[list[int], Volume]:
    """``load_volume(path, threads=2, processes=True)`` and the process count of each decode pool that ran (a pool
    that ran is closed; one given up at start is not, so it is not counted)."""
    import engine.io.procs as procs
    from engine.io import load_volume

    used: list[int] = []
    real = procs.DecodePool.close

    def spy(pool: procs.DecodePool) -> None:
        used.append(len(pool.pool._processes or {}))  # type: ignore[attr-defined]
        real(pool)

    procs.DecodePool.close = spy  # type: ignore[method-assign]
    try:
        vol = load_volume(path, threads=2, processes=True)
    finally:
        procs.DecodePool.close = real  # type: ignore[method-assign]
    return used, vol
