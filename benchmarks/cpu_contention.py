"""CPU contention probe: how much one busy vCPU slows a single-threaded loop on another, and how fast two pinned
thread pools run alone and side by side (the question behind issue 29: do two workers' CPU shares slow each other?).
The workers' CPU shares (``cpu_shares``, the throughput benchmark's ``--cpu-layout``) are defined here.

    python -m benchmarks.cpu_contention [--seconds 0.6] --out result.json

``pair_with_first``: the rate of a zlib-inflate loop pinned to the first CPU while a second one runs on CPU j, over
its rate alone (a hyper-thread sibling shows about 0.5-0.6; a separate core about 1.0; a uniform drop on every j is
the package's clock or shared cache, not placement). ``pools``: inflate calls per second of one process with one
thread per CPU of its set, alone and beside the complementary set (the layouts "blocks" and "halves" of
``cpu_shares``, and even/odd), so a layout that keeps two workers off each other's cores would show here (the
committed ``cpu_contention_2xh100.json`` calls blocks "low_high" and halves "quarters", as the first version did).
Each loop inflates ~1 MB per call (zlib releases the GIL), the work of a slice decoder.
"""

from __future__ import annotations

import argparse
import datetime as dt
import multiprocessing as mp
import os
import platform
import threading
import time
import zlib
from pathlib import Path
from typing import Any

from benchmarks.report import write_json

DATA = zlib.compress(os.urandom(1 << 16) * 16, 1)  # ~1 MB out per call


def _loop(cpu: int, seconds: float, queue: Any) -> None:
    os.sched_setaffinity(0, {cpu})
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        zlib.decompress(DATA)
        n += 1
    queue.put((cpu, n / (time.perf_counter() - t0)))


def _at_once(target: Any, firsts: list[Any], seconds: float) -> dict[Any, float]:
    """``target(first, seconds, queue)`` in one process per entry of ``firsts``, all at once: what each put."""
    queue: Any = mp.Queue()
    procs = [mp.Process(target=target, args=(first, seconds, queue)) for first in firsts]
    for p in procs:
        p.start()
    out = dict(queue.get() for _ in procs)
    for p in procs:
        p.join()
    return out


def rates(cpus: list[int], seconds: float) -> dict[int, float]:
    """Calls per second of one single-threaded loop per CPU in ``cpus``, all running at once."""
    return _at_once(_loop, cpus, seconds)


def _pool(cpuset: list[int], seconds: float, queue: Any) -> None:
    os.sched_setaffinity(0, set(cpuset))
    stop = time.perf_counter() + seconds
    counts = [0] * len(cpuset)

    def work(i: int) -> None:
        while time.perf_counter() < stop:
            zlib.decompress(DATA)
            counts[i] += 1

    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(cpuset))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    queue.put((tuple(cpuset), sum(counts) / seconds))


def pools(*cpusets: list[int], seconds: float) -> list[dict[str, Any]]:
    """Inflate calls per second of one process per CPU set (a thread per CPU), all at once."""
    found = _at_once(_pool, list(cpusets), seconds)
    return [{"cpus": list(s), "calls_per_second": round(found[tuple(s)], 1)} for s in cpusets]


def cpu_shares(workers: int, cpus: list[int] | None = None, layout: str = "blocks") -> list[list[int]]:
    """``cpus`` (default this process's) split into ``workers`` equal, disjoint shares (a remainder is left unused):
    "blocks", one run of CPUs each; "halves", each share half from the first half of the CPUs and half from the
    second (where a host numbers hyper-thread siblings i and i + n/2, each worker then owns whole cores)."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    per = max(1, len(cpus) // workers)
    if layout == "halves" and per >= 2 and len(cpus) >= 2 * workers:
        half, part = len(cpus) // 2, per // 2
        return [cpus[i * part : (i + 1) * part] + cpus[half + i * part : half + (i + 1) * part] for i in range(workers)]
    return [cpus[(i * per) % len(cpus) : (i * per) % len(cpus) + per] for i in range(workers)]


def layouts(cpus: list[int]) -> dict[str, list[list[int]]]:
    """Two disjoint halves of ``cpus`` three ways: the throughput benchmark's "blocks" and "halves" (``cpu_shares``)
    and even/odd positions."""
    h = len(cpus) // 2
    return {
        "blocks": cpu_shares(2, cpus, "blocks"),
        "halves": cpu_shares(2, cpus, "halves"),
        "even_odd": [cpus[0 : 2 * h : 2], cpus[1 : 2 * h : 2]],
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=0.6, help="each measurement's length")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise SystemExit("needs at least two CPUs")
    solo = rates([cpus[0]], args.seconds)[cpus[0]]
    report: dict[str, Any] = {
        "benchmark": "cpu_contention",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "cpus": len(cpus), "python": platform.python_version()},
        "solo_calls_per_second": round(solo, 1),
        "pair_with_first": {str(j): round(rates([cpus[0], j], args.seconds)[cpus[0]] / solo, 3) for j in cpus[1:]},
        "pools": {},
    }
    for name, (a, b) in layouts(cpus).items():
        report["pools"][name] = {"alone": pools(a, seconds=args.seconds), "together": pools(a, b, seconds=args.seconds)}
    write_json(args.out, report)


if __name__ == "__main__":
    main()
