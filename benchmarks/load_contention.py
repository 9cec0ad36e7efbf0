"""Loading a PNG stack, alone and beside a second loader: where a worker's load time goes when two run (issue 29).

    python -m benchmarks.load_contention [--phantom 476,1024,1024 | --input scan.zip] [--loads 5] --out result.json

One process (pinned to the first half of this process's CPUs, one decode thread per CPU, or ``--threads``) loads
the stack ``--loads`` times after a warm-up load, then two such processes (the two halves) load at once, each load
timed with its user and system CPU seconds and minor page faults. Each is done twice: into a fresh ``np.empty`` per
load ("fresh", as the CLI does) and into one reused buffer (``engine.staging.VolumeBuffer``, as a worker does;
page-locked with ``--pinned`` on a CUDA host). ``--unfilter host,device`` compares libpng's unfiltering on the host
with the device's (``engine.io.png_rows``; the i-th process on the i-th of ``--gpus``), ``--buffers reused`` skips
the fresh arrays. The committed ``loadprobe_2xh100.json`` came from the first version
of this probe (the same measurements, the buffer reused by patching the loader).
"""

from __future__ import annotations

import argparse
import datetime as dt
import multiprocessing as mp
import os
import platform
import resource
import statistics
import tempfile
import time
from pathlib import Path
from queue import Empty
from typing import Any

from benchmarks.report import write_json

SPACING = (1.0, 1.0, 1.0)


def _loads(
    path: Path,
    cpus: list[int],
    threads: int,
    reuse: bool,
    pinned: bool,
    n: int,
    queue: Any,
    start: Any,
    gpu: str | None = None,
) -> None:
    """``n`` timed loads of ``path`` on ``threads`` decode threads in this process, pinned to ``cpus`` (after a
    warm-up and ``start``); with ``gpu``, PNG rows unfiltered there."""
    os.sched_setaffinity(0, set(cpus))
    from engine.backend.select import get_backend
    from engine.io import load_volume
    from engine.io.png_rows import DeviceRows
    from engine.staging import VolumeBuffer

    allocate = VolumeBuffer(pinned=pinned) if reuse else None
    buffer = VolumeBuffer(pinned=pinned) if reuse else None
    backend = None if gpu is None else get_backend(gpu)
    unfilter = None if backend is None or backend.is_host else DeviceRows(backend, buffer)
    kwargs = {"spacing_zyx_mm": SPACING, "threads": threads, "allocate": allocate, "rows": unfilter}
    load_volume(path, **kwargs)  # type: ignore[arg-type]  # page cache, imports, kernels
    start.wait()
    rows = []
    for _ in range(n):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        volume = load_volume(path, **kwargs)  # type: ignore[arg-type]
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        rows.append(
            {
                "seconds": round(time.perf_counter() - t0, 4),
                "user": round(r1.ru_utime - r0.ru_utime, 3),
                "sys": round(r1.ru_stime - r0.ru_stime, 3),
                "minor_faults": r1.ru_minflt - r0.ru_minflt,
            }
        )
        del volume
    queue.put((cpus, rows))


def phase(
    path: Path,
    cpusets: list[list[int]],
    threads: int,
    reuse: bool,
    pinned: bool,
    n: int,
    gpus: list[str] | None = None,
) -> list[dict[str, Any]]:
    """Each CPU set's loads (``threads`` decode threads each; the i-th set's rows unfiltered on ``gpus[i]``), the
    sets loading at the same time."""
    ctx = mp.get_context("fork")
    queue, start = ctx.Queue(), ctx.Barrier(len(cpusets))
    procs = [
        ctx.Process(target=_loads, args=(path, c, threads, reuse, pinned, n, queue, start, gpus[i] if gpus else None))
        for i, c in enumerate(cpusets)
    ]
    for p in procs:
        p.start()
    out = [_result(queue, procs) for _ in procs]
    for p in procs:
        p.join()
    return [
        {
            "cpus": f"{c[0]}-{c[-1]}",
            "loads": rows,
            "median_seconds": statistics.median(r["seconds"] for r in rows),
            "median_sys": statistics.median(r["sys"] for r in rows),
        }
        for c, rows in out
    ]


def _result(queue: Any, procs: list[Any], timeout: float = 600) -> Any:
    """The next result; an error at once where a loader process died (e.g. no Warp for the reused buffer, or
    ``--pinned`` without CUDA)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            return queue.get(timeout=0.5)
        except Empty:
            dead = [p for p in procs if p.exitcode not in (None, 0)]
            if dead:
                raise RuntimeError(f"a loader process exited with {dead[0].exitcode}; its error is above") from None
    raise TimeoutError(f"no load finished within {timeout} s")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--phantom", default="476,1024,1024", help="z,y,x of the bone phantom's PNG zip")
    parser.add_argument("--input", type=Path, help="a PNG stack (zip or folder) instead of the phantom")
    parser.add_argument("--loads", type=int, default=5, help="timed loads per process and phase")
    parser.add_argument("--pinned", action="store_true", help="the reused buffer page-locked (needs CUDA)")
    parser.add_argument(
        "--threads", default="", help="decode threads per process, comma-separated to compare (default: its CPUs)"
    )
    parser.add_argument("--unfilter", default="host", help="host, device, or both comma-separated to compare")
    parser.add_argument("--gpus", default="cuda:0,cuda:1", help="the devices of --unfilter device, one per process")
    parser.add_argument("--buffers", default="fresh,reused", help="fresh, reused, or both comma-separated")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    cpus = sorted(os.sched_getaffinity(0))
    half = max(1, len(cpus) // 2)
    sets = [cpus[:half], cpus[half : 2 * half] or cpus[:half]]
    path = args.input
    prep = None
    if path is None:
        from benchmarks.phantom_zip import write_phantom_zip

        shape = tuple(int(v) for v in args.phantom.split(","))
        path = Path(tempfile.mkdtemp(prefix="bonemesh-load-")) / "phantom.zip"
        prep = write_phantom_zip(shape, path)  # type: ignore[arg-type]
    report: dict[str, Any] = {
        "benchmark": "load_contention",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "cpus": len(cpus), "python": platform.python_version()},
        "input": {"name": path.name, "bytes": path.stat().st_size if path.is_file() else None, "preparation": prep},
        "pinned": args.pinned,
    }
    gpus = args.gpus.split(",")
    for unfilter in args.unfilter.split(","):
        for threads in [int(t) for t in args.threads.split(",") if t] or [half]:
            prefix = ("" if not args.threads else f"threads_{threads}_") + ("" if unfilter == "host" else "device_")
            for reuse in [b == "reused" for b in args.buffers.split(",")]:
                key = prefix + ("reused" if reuse else "fresh")
                on = gpus if unfilter == "device" else None
                report[f"{key}_alone"] = phase(path, sets[:1], threads, reuse, args.pinned, args.loads, on)
                report[f"{key}_both"] = phase(path, sets, threads, reuse, args.pinned, args.loads, on)
                alone = report[f"{key}_alone"][0]["median_seconds"]
                both = [p["median_seconds"] for p in report[f"{key}_both"]]
                print(f"[load_contention] {key}: alone {alone:.3f} s, both {both}", flush=True)
                write_json(args.out, report)


if __name__ == "__main__":
    main()
