"""A fresh worker's first loads: the warm-up (``engine.job.warmup``) with and without the load buffers page-locked for
the scan's size, then the loads a worker's first jobs make.

    python -m benchmarks.first_load [--phantom 476,1024,1024] [--device cuda:0] [--threads 16] [--loads 3]
                                    [--reserve 0,scan] --out result.json

The bone phantom is written as a zip of 16-bit PNG slices (``benchmarks.phantom_zip``, what ``throughput``
uploads). For each ``--reserve`` (bytes, ``scan``: the phantom's 16-bit volume, ``0``: nothing page-locked at the
warm-up), a new Python process (nothing allocated or loaded yet, as a new worker) warms ``--device`` up with that
``volume_bytes`` and loads the stack ``--loads`` times as the worker does (``load_volume`` into the process's
``pinned_volumes``, PNG rows unfiltered on the device where it is a GPU: ``device_rows``). Each load's wall and
process CPU seconds are reported; the first against the next ones is what a fresh worker's first job pays. Off
CUDA nothing is page-locked, so both reserves measure the same path there.

Measured on one H100, 16 threads, the 476 x 1024 x 1024 phantom (``benchmarks/results/first_load_h100.json``):
without the reserve the first load took 1.63 s and the next 0.41-0.45 s; with it, 0.55 s and then 0.42-0.50 s
(the warm-up 2.6 s, 2.1 GiB page-locked). On the 2 x H100 host the same steps, in a script before they became this
module (``firstload_2xh100.json``): 1.66 s then 0.54-0.65 s, against 0.63 s then 0.57-0.70 s.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.report import write_json


def _child(args: argparse.Namespace) -> dict[str, Any]:
    """In the new process: warm up, then the timed loads."""
    from engine.device import init_runtime

    init_runtime(os.environ.get("WARP_CACHE_PATH"))
    from engine.io import load_volume
    from engine.io.png_rows import device_rows
    from engine.job.warmup import warm_up
    from engine.staging import pinned_volumes

    t0 = time.perf_counter()
    info = warm_up(args.device, volume_bytes=args.child_reserve)
    warm = time.perf_counter() - t0
    loads = []
    for _ in range(args.loads):
        wall, cpu = time.perf_counter(), time.process_time()
        volume = load_volume(
            args.child_zip,
            spacing_zyx_mm=(0.05, 0.05, 0.05),
            threads=args.threads,
            allocate=pinned_volumes(args.device),
            rows=device_rows(args.device),
        )
        loads.append({"seconds": time.perf_counter() - wall, "cpu_seconds": time.process_time() - cpu})
        del volume  # the next load may take the buffer again
    return {"warm_up": info, "warm_up_wall_seconds": warm, "loads": loads}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--phantom", default="476,1024,1024", help="the bone phantom's shape Z,Y,X")
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--threads", type=int, default=None, help="decode threads (default: the CPUs)")
    parser.add_argument("--loads", type=int, default=3)
    parser.add_argument("--reserve", default="0,scan", help="volume_bytes of each process's warm-up (scan, bytes)")
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--child-zip", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--child-reserve", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_zip is not None:  # the measured process: its result as JSON on stdout's last line
        print(json.dumps(_child(args)))
        return 0

    from benchmarks.phantom_zip import write_phantom_zip

    shape = tuple(int(v) for v in args.phantom.split(","))
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bonemesh-first-load-"))
    workdir.mkdir(parents=True, exist_ok=True)
    archive = workdir / "phantom.zip"
    prep = write_phantom_zip(shape, archive)  # type: ignore[arg-type]
    scan = 2 * shape[0] * shape[1] * shape[2]
    report: dict[str, Any] = {
        "benchmark": "first_load",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "device": args.device,
        "input": {"shape_zyx": shape, "archive_bytes": prep["archive_bytes"], "volume_bytes": scan},
        "runs": [],
    }
    for text in args.reserve.split(","):
        reserve = scan if text.strip() == "scan" else int(text)
        argv_child = [sys.executable, "-m", "benchmarks.first_load", "--out", str(args.out), "--device", args.device]
        argv_child += ["--loads", str(args.loads), "--child-zip", str(archive), "--child-reserve", str(reserve)]
        if args.threads:
            argv_child += ["--threads", str(args.threads)]
        done = subprocess.run(argv_child, capture_output=True, text=True, timeout=900, check=False)
        if done.returncode:
            raise SystemExit(f"the process for reserve {reserve} failed:\n{done.stderr[-4000:]}")
        run = json.loads(done.stdout.strip().splitlines()[-1])
        report["runs"].append({"reserve_bytes": reserve, **run})
        firsts = ", ".join(f"{x['seconds']:.3f}" for x in run["loads"])
        print(f"[first_load] reserve {reserve:,} B: warm-up {run['warm_up_wall_seconds']:.2f} s, loads {firsts} s")
    write_json(args.out, report)
    archive.unlink()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
