"""Status reads while uploads stream: latency of ``GET /v1/jobs/{id}`` under concurrent uploads (issue 15, item 10).

    python -m benchmarks.status_latency [--uploads 50] [--shape 96,256,256] [--pollers 2] [--workers 0]
                                        [--repeat 1] [--redis-server PATH] [--workdir DIR] --out result.json

It starts a redis-server, ``bonemesh serve`` (and ``--workers`` CPU workers, none by default: the API alone is
measured) with a fresh data folder (the helpers of ``tests/service/procs.py``), submits one job to poll, then
POSTs ``--uploads`` slice archives at once (each a zip of 16-bit PNG slices of the bone phantom, written
beforehand, sent by its own thread) while ``--pollers`` processes (apart from the uploading threads' GIL) GET
the job back to back. It records every status
read that started while uploads were in flight (p50, p90, p99, max), and each upload's duration and status.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks.report import stop_on_sigterm
from tests.service.procs import RedisServer, ServiceStack


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def write_archive(shape: tuple[int, int, int], path: Path) -> int:
    """The bone phantom as a zip of 16-bit PNG slices (stored, ``benchmarks.phantom_zip``); returns its size."""
    from benchmarks.phantom_zip import write_phantom_zip

    return int(write_phantom_zip(shape, path)["archive_bytes"])


def _poll(base_url: str, job_id: str, start: Any, stop: Any, out: Any) -> None:
    """Read the job's status back to back (in a process of its own: the uploading threads' GIL is not ours);
    puts (seconds, status) of each read that started between ``start`` and ``stop`` on ``out``."""
    reads: list[tuple[float, int]] = []
    with httpx.Client(base_url=base_url, headers={"X-API-Key": "key-a"}, timeout=60) as c:
        start.wait()
        while not stop.is_set():
            t0 = time.perf_counter()
            r = c.get(f"/v1/jobs/{job_id}")
            reads.append((time.perf_counter() - t0, r.status_code))
    out.put(reads)


def measure(base_url: str, archive: Path, uploads: int, pollers: int, params: dict[str, Any]) -> dict[str, Any]:
    """One round: a job to poll, then ``uploads`` concurrent uploads while ``pollers`` processes read its status."""
    import multiprocessing as mp

    headers = {"X-API-Key": "key-a"}
    with httpx.Client(base_url=base_url, headers=headers, timeout=600) as c, open(archive, "rb") as fh:
        resp = c.post("/v1/jobs", files={"file": ("a.zip", fh)}, data={"params": json.dumps(params)})
        resp.raise_for_status()
        job_id = resp.json()["id"]
    ctx = mp.get_context("spawn")
    start, stop, out = ctx.Event(), ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_poll, args=(base_url, job_id, start, stop, out)) for _ in range(pollers)]
    for p in procs:
        p.start()
    time.sleep(2.0)  # the pollers are connected

    def upload(_: int) -> tuple[float, int]:
        with httpx.Client(base_url=base_url, headers=headers, timeout=600) as c, open(archive, "rb") as fh:
            t0 = time.perf_counter()
            r = c.post("/v1/jobs", files={"file": ("a.zip", fh)}, data={"params": json.dumps(params)})
            return time.perf_counter() - t0, r.status_code

    start.set()
    t0 = time.perf_counter()
    with ThreadPoolExecutor(uploads) as pool:
        results = list(pool.map(upload, range(uploads)))
    wall = time.perf_counter() - t0
    stop.set()
    reads = [r for _ in procs for r in out.get(timeout=60)]
    for p in procs:
        p.join(timeout=60)
    ms = [dt * 1000 for dt, _ in reads]
    durations = [d for d, _ in results]
    return {
        "status_reads": len(ms),
        "status_errors": sorted({code for _, code in reads if code != 200}),
        "status_ms": {
            "p50": _percentile(ms, 50),
            "p90": _percentile(ms, 90),
            "p99": _percentile(ms, 99),
            "max": max(ms) if ms else float("nan"),
            "mean": statistics.fmean(ms) if ms else float("nan"),
        },
        "uploads_wall_s": wall,
        "upload_s": {"p50": _percentile(durations, 50), "max": max(durations)},
        "upload_statuses": sorted({s for _, s in results}),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--uploads", type=int, default=50)
    parser.add_argument("--shape", default="96,256,256", help="phantom shape Z,Y,X of each uploaded archive")
    parser.add_argument("--pollers", type=int, default=2)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--label", default="", help="free text stored with the result (e.g. the commit)")
    parser.add_argument("--redis-server", default=None, help="redis-server executable (default: PATH or apt-get)")
    parser.add_argument("--workdir", type=Path, default=None, help="archive, data and logs (default: a temp dir)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    shape = tuple(int(v) for v in args.shape.split(","))
    assert len(shape) == 3
    with tempfile.TemporaryDirectory(prefix="bonemesh-status-") as tmp:
        root = args.workdir or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        archive = root / "phantom.zip"
        size = write_archive(shape, archive)  # type: ignore[arg-type]
        from benchmarks.phantom import BONE_LEVEL

        params = {"iso": BONE_LEVEL, "spacing": [0.5, 0.5, 0.5]}
        rounds = []
        stop_on_sigterm()  # `timeout`: the with-blocks below stop every process
        with (
            RedisServer(root / "redis", args.redis_server) as redis,
            ServiceStack(root / "stack", redis.url, max_upload_bytes=1 << 30) as stack,
        ):
            stack.start_server()
            for _ in range(args.workers):
                stack.start_worker()
            for k in range(args.repeat):
                result = measure(stack.base_url, archive, args.uploads, args.pollers, params)
                print(f"round {k + 1}: {json.dumps(result)}", flush=True)
                rounds.append(result)
    out = {
        "benchmark": "status reads under concurrent uploads",
        "label": args.label,
        "uploads": args.uploads,
        "archive_bytes": size,
        "shape_zyx": list(shape),
        "pollers": args.pollers,
        "workers": args.workers,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0]},
        "rounds": rounds,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
