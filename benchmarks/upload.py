"""Upload benchmark: how fast ``POST /v1/jobs`` takes a large scan archive in, with real processes.

    python -m benchmarks.upload [--phantom Z,Y,X | --input scan.zip --params JSON] [--repeat N]
                                [--clients httpx,curl] [--api-workers N] [--baseline CHECKOUT] [--predecode on|off]
                                --out result.json

It starts a redis-server on a free loopback port and ``bonemesh serve`` (``tests/service/procs.py``; no worker: the
jobs stay queued), then POSTs the archive ``repeat`` times with each client, one after another: httpx (as
``benchmarks.service`` and most Python clients send it) and curl (``-F``, ``Expect`` off). A POST's time runs from
its start to the 202, so it holds the multipart parsing, the write to storage and its fsync, the archive's
inspection and the job's record. Throughput is the archive's bytes over that time; the median per client is the
result. The archive (default: the bone phantom as 16-bit PNG slices, ``benchmarks.phantom_zip``) is written
beforehand and not timed. A PNG zip's slices are decoded by the API while it arrives (issue 46 item 4, on by
default); ``--predecode off`` times the upload without it.

``--baseline`` names another checkout of bonemesh (e.g. ``git worktree add /tmp/before <commit>``): a second
server runs its code (``PYTHONPATH``) beside this one, on the same data folder, broker and database, and every
round POSTs to both, one after the other (alternating which goes first), so the two are compared in the same run
under the same conditions; the JSON gives each one's medians and the ratio.

``--compare-env K=V[,K=V]`` does the same with a second server of this code whose settings differ (e.g.
``BONEMESH_PREDECODE_MIN_BYTES=0``), and ``--side-by-side N`` makes every round N POSTs at once to each server
(each client a thread; every POST's time is kept, and each round's wall time under ``round_seconds``), as when
several users upload at the same time:

    python -m benchmarks.upload --input cranium_ct_png16.zip --params '{"preset": "bone", "hu_offset": 1024,
        "spacing": [1.5, 0.957, 0.957]}' --clients httpx --api-workers 2 --side-by-side 4 --repeat 6 \
        --compare-env BONEMESH_PREDECODE_MIN_BYTES=0 --out benchmarks/results/upload_cpu_small_side_by_side.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import shutil
import statistics
import subprocess
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx

from benchmarks.report import stop_on_sigterm, write_json
from tests.service.procs import API_KEYS, RedisServer, ServiceStack

PHANTOM_PARAMS = {"preset": "bone", "hu_offset": 1024, "spacing": [0.05, 0.05, 0.05]}


def post_httpx(url: str, archive: Path, params: dict[str, Any]) -> tuple[int, float]:
    t0 = time.perf_counter()
    with httpx.Client(base_url=url, headers={"X-API-Key": API_KEYS[0]}, timeout=3600) as client:
        with open(archive, "rb") as fh:
            resp = client.post(
                "/v1/jobs",
                files={"file": (archive.name, fh, "application/zip")},
                data={"params": json.dumps(params)},
            )
    return resp.status_code, time.perf_counter() - t0


def post_curl(url: str, archive: Path, params: dict[str, Any]) -> tuple[int, float]:
    argv = ["curl", "-s", "-o", "/dev/null", "-w", "%{http_code}", "-H", f"X-API-Key: {API_KEYS[0]}", "-H", "Expect:"]
    argv += ["-F", f"file=@{archive};type=application/zip", "-F", f"params={json.dumps(params)}", f"{url}/v1/jobs"]
    t0 = time.perf_counter()
    out = subprocess.run(argv, capture_output=True, text=True, check=False)
    return int(out.stdout or 0), time.perf_counter() - t0


CLIENTS = {"httpx": post_httpx, "curl": post_curl}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--phantom", default="300,1024,1024", help="Z,Y,X of the phantom archive (default 300 slices)")
    ap.add_argument("--input", default=None, help="a scan archive instead of the phantom")
    ap.add_argument("--params", default=None, help="JSON params for --input")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--clients", default="httpx,curl")
    ap.add_argument("--api-workers", type=int, default=1)
    ap.add_argument("--baseline", default=None, help="another checkout whose server is timed in the same run")
    ap.add_argument(
        "--predecode",
        choices=("on", "off"),
        default="on",
        help="BONEMESH_DECODE_DURING_UPLOAD: a PNG zip's slices decoded by the API while it arrives (issue 46)",
    )
    ap.add_argument("--compare-env", default=None, help="K=V[,K=V]: a second server of this code with these settings")
    ap.add_argument("--side-by-side", type=int, default=1, help="POSTs at once to a server in each round")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    clients = [c for c in args.clients.split(",") if c]
    if "curl" in clients and shutil.which("curl") is None:
        print("curl: skipped (not installed)")
        clients.remove("curl")
    root = Path(args.workdir or tempfile.mkdtemp(prefix="bonemesh-upload-"))
    root.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {
        "benchmark": "upload",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "python": platform.python_version()},
        "api_workers": args.api_workers,
        "repeat": args.repeat,
        "decode_during_upload": args.predecode == "on",
    }
    if args.input:
        archive, params = Path(args.input), json.loads(args.params or "{}")
        result["input"] = {"archive": archive.name}
    else:
        from benchmarks.phantom_zip import write_phantom_zip

        shape = tuple(int(x) for x in args.phantom.split(","))
        archive, params = root / "phantom.zip", PHANTOM_PARAMS
        result["input"] = {"phantom_zyx": list(shape), **write_phantom_zip(shape, archive)}  # type: ignore[arg-type]
    size = archive.stat().st_size
    result["input"]["archive_bytes"] = size
    result["clients"] = {}
    limit = size + (1 << 20)
    stop_on_sigterm()  # `timeout`: the with-blocks below stop every process
    predecode = {"BONEMESH_DECODE_DURING_UPLOAD": "true" if args.predecode == "on" else "false"}
    with (
        RedisServer(root / "redis") as redis,
        ServiceStack(root / "stack", redis.url, max_upload_bytes=limit, extra_env=predecode) as stack,
    ):
        servers = {"current": stack.start_server(workers=args.api_workers)}
        if args.baseline:
            env = {"PYTHONPATH": str(Path(args.baseline).resolve())}
            servers["baseline"] = stack.start_server(workers=args.api_workers, extra_env=env)
            result["baseline"] = str(Path(args.baseline).resolve())
        if args.compare_env:
            env = dict(kv.split("=", 1) for kv in args.compare_env.split(",") if kv)
            servers["compare"] = stack.start_server(workers=args.api_workers, extra_env=env)
            result["compare_env"] = env
        result["side_by_side"] = args.side_by_side
        for name in clients:
            runs: dict[str, list[float]] = {label: [] for label in servers}
            rounds: dict[str, list[float]] = {label: [] for label in servers}
            post = CLIENTS[name]
            with ThreadPoolExecutor(args.side_by_side) as pool:
                for i in range(args.repeat):
                    order = list(servers) if i % 2 == 0 else list(reversed(servers))
                    for label in order:
                        t0 = time.perf_counter()
                        posts = list(
                            pool.map(
                                lambda _, u=servers[label], f=post: f(u, archive, params), range(args.side_by_side)
                            )
                        )
                        rounds[label].append(time.perf_counter() - t0)
                        for status, seconds in posts:
                            if status != 202:
                                raise SystemExit(f"{name} POST {i + 1} to {label}: HTTP {status}\n{stack.logs()}")
                            runs[label].append(seconds)
                        times = ", ".join(f"{s:.2f}" for _, s in posts)
                        print(f"{name} #{i + 1} {label}: {times} s, {size / posts[0][1] / 1e6:.0f} MB/s", flush=True)
            entry: dict[str, Any] = {}
            for label, times in runs.items():
                med = statistics.median(times)
                entry[label] = {"seconds": times, "median_seconds": med, "median_mb_per_s": size / med / 1e6}
                entry[label]["round_seconds"] = rounds[label]
            for other in ("baseline", "compare"):
                if other in entry:
                    key = "speedup" if other == "baseline" else "compare_over_current"
                    entry[key] = entry[other]["median_seconds"] / entry["current"]["median_seconds"]
            result["clients"][name] = entry
            write_json(Path(args.out), result)
    write_json(Path(args.out), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
