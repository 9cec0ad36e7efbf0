"""Throughput benchmark: N jobs through 1 worker, then through one worker per device, with real processes.

    python -m benchmarks.throughput --devices cuda:0,cuda:1 [--jobs 8] [--input scan.zip --params JSON]
                                    [--phantom Z,Y,X] [--redis-server PATH] [--workdir DIR] [--warp-cache DIR]
                                    --out result.json
    python -m benchmarks.throughput --devices cpu,cpu --jobs 6 --out benchmarks/results/throughput_cpu.json

It starts a redis-server on a free loopback port and ``bonemesh serve`` (``tests/service/procs.py``), then runs
two phases on the same input, each with fresh workers: first one worker (the first device), then one worker per
entry of ``--devices``. A phase POSTs the N jobs at once and ends when the last one has succeeded; its time is from
the first POST to the last job's ``finished_at``; the jobs are uploaded by ``--uploaders`` clients side by side
(default 2) to ``--api-workers`` API processes (default 2), and each phase's workers are ready and, on a GPU,
warmed up (``BONEMESH_WARMUP``) before the first POST, as long-running workers are. The ratio of the two is the
scaling (the issue asks >= 1.8x for 2 GPUs). A warm-up job first fills the shared Warp kernel cache (a fresh one
under the work folder, or ``--warp-cache``: an existing cache skips the compilation), so no phase pays for it.

Each worker is pinned with ``taskset`` to its own share of the CPUs (the workers' CPUs split evenly between the
workers of the larger phase; the single worker of the first phase gets the same share), so on a CPU-only host the
two phases compare like with like: Warp's CPU kernels, the ingest threads (``engine.io.decode_threads`` reads the
affinity mask) and the BLAS/OpenMP pools (``OMP_NUM_THREADS`` etc. set to the share) use only the worker's own
cores. ``--front-cpus N`` keeps N CPUs for the API processes, Redis and the upload clients (default 0: they share
every CPU). On the 2 x H200 host it made no difference with 2 uploaders (1.76x with 4 kept, 1.77x without, 12 jobs);
what did was the number of uploads at once: 4 uploaders made each 570 MB upload take 3.6 s and slowed the jobs
running meanwhile (decimation 0.8 s instead of 0.27 s): 1.51x against 1.66-1.77x with 2 (docs/benchmarks.md).

``--mode queued`` (or ``both``: uploading, then queued) uploads every job while the phase's workers are paused
(SIGSTOP to each worker's process group) and times the phase from their resume: the workers' own scaling, without
the uploads sharing the host's CPUs. ``--cpu-layout halves`` gives each worker half of its CPUs from each half of
the host's (whole cores where hyper-thread siblings are numbered i and i + n/2; on the 2 x H100 host it made no
difference: 1.81x against 1.80x). ``--workdir`` holds the stack's data folder, which takes every upload: on the 2 x
H100 VM its disk took 24 uploads of 571 MB in 15.5-17 s (workers paused) against 7.3 s on tmpfs (``/dev/shm``), so
two fast workers starved behind uploads to disk (1.39x) and reached 1.71-1.80x with the folder on tmpfs.

Input: ``--input`` (a scan archive, with ``--params``), ``--phantom Z,Y,X`` (the bone phantom as 16-bit PNG slices,
``benchmarks.phantom_zip``), or by default the bundled CT head (``engine.data``).

Where the time goes, per phase: ``jobs_detail`` (per job: its worker, the client's POST seconds, start and end from
the first POST, the worker's seconds per step from its ``job <id> timings`` log line (``worker.tasks``: claim, load,
reconstruct, write_files, publish, queue_wait, ...) and the engine's per stage from the job's report.json),
``stage_medians`` (the median of each), ``first_start_seconds``, ``last_upload_done_seconds`` and the host's
``load_average_at_end``; ``after_first_jobs_per_minute`` is the rate once each worker has finished its first job,
and ``after_first_speedups`` its ratios (the phases' start and tail left out).

The workers warm up as the product's do (``BONEMESH_WARMUP``, on every device; ``--warmup``), and with
``--phantom`` they page-lock their load buffers for the phantom's volume (``--warmup-volume-bytes scan``), as a
worker whose operator set ``BONEMESH_WARMUP_VOLUME_BYTES`` for the usual scans does. Before either, each phase's
fresh workers paid for both in their first job: 1.2-2.1 s more on the 2 x H100 host (its load), 1.5 s on the CPU.

``--rounds N`` repeats the phases, one worker first in even rounds and all first in odd ones, so that a slow spell
of the host (on the 2 x H100 VM, loads of 0.9-1.2 s for a few seconds against 0.45-0.55 s) falls on either side:
round 0's phases keep the top-level keys, later rounds are under ``more_rounds``, and ``speedups`` /
``median_speedup`` give every round's ratio and their median. Each phase's jobs are deleted once measured, so the
data folder holds one phase's uploads and files at most.

The JSON is rewritten after each phase, and SIGTERM (``timeout``) stops the processes and keeps what was measured.
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import json
import multiprocessing
import os
import platform
import signal
import statistics
import sys
import tempfile
import time
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx

from benchmarks.cpu_contention import cpu_shares
from benchmarks.report import stop_on_sigterm, write_json
from benchmarks.timing_lines import api_timings, worker_timings
from tests.service.procs import (
    API_KEYS,
    Proc,
    RedisServer,
    ServiceStack,
    bonemesh_argv,
    submit,
    wait_for_job,
    wait_until,
)

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def split_front(front: str) -> tuple[list[int], list[int]]:
    """This process's CPUs as (the front's: API, Redis and the upload clients; the workers'): ``front`` CPUs off the
    end ("auto": 4 on a host of 16 or more, else none; "0": none, every CPU shared)."""
    cpus = sorted(os.sched_getaffinity(0))
    n = (4 if len(cpus) >= 16 else 0) if front == "auto" else int(front)
    if not 0 <= n < len(cpus):
        raise SystemExit(f"--front-cpus {front}: expected 0 to {len(cpus) - 1}")
    return (cpus[-n:], cpus[:-n]) if n else ([], cpus)


def start_worker(stack: ServiceStack, index: int, device: str, cpus: list[int]) -> Proc:
    """A ``bonemesh worker`` on ``device`` pinned to ``cpus``, registered with ``stack`` (stopped by its close)."""
    env = {**stack.env, "BONEMESH_DEVICE": device, **{v: str(len(cpus)) for v in THREAD_VARS}}
    argv = ["taskset", "-c", ",".join(map(str, cpus)), *bonemesh_argv(), "worker"]
    argv += ["--hostname", f"bench{index}-{os.getpid()}@%h"]
    proc = Proc(f"worker-{index}", argv, stack.log_dir / f"bench-worker-{index}-{time.time_ns()}.log", env, stack.root)
    stack.workers.append(proc)
    return proc


def _ready(proc: Proc, warm: bool) -> bool:
    """Celery's ready line, and for a worker that warms its device up, the end of the warm-up."""
    if not proc.alive():
        raise RuntimeError(f"{proc.describe()}:\n{proc.tail()}")
    log = proc.tail(20000)
    return " ready." in log and (not warm or " warm in " in log or "warm-up failed" in log)


def _warms_up(stack: ServiceStack, device: str) -> bool:
    """Whether a worker of ``stack`` on ``device`` warms up at start (``worker.app.warms_up``: its
    ``BONEMESH_WARMUP``, on by default on a GPU)."""
    from core.settings import Settings
    from worker.app import warms_up

    return warms_up(Settings(device=device, warmup=stack.env.get("BONEMESH_WARMUP", "auto")))


def _post(base_url: str, archive: Path, params: dict[str, Any], _: int) -> tuple[str, float, float]:
    """One upload by a client (a thread, or a process with ``--upload-processes``): the job's id, and the POST's
    start and end."""
    with httpx.Client(base_url=base_url, headers={"X-API-Key": API_KEYS[0]}, timeout=600) as client:
        start = time.time()
        resp = submit(client, archive, params)
        assert resp.status_code == 202, resp.text
        return resp.json()["id"], start, time.time()


def _phases(mode: str, devices: list[str], round_: int = 0) -> list[tuple[str, list[str], bool]]:
    """The phases of a round: (report key, its devices, queued), per mode; one worker first, then all, in even
    rounds, and the other way round in odd ones (a slow spell of the host then falls on either side)."""
    out = []
    for queued in {"uploading": (False,), "queued": (True,), "both": (False, True)}[mode]:
        prefix = "queued_" if queued else ""
        pair = [(f"{prefix}one_worker", devices[:1], queued), (f"{prefix}all_workers", devices, queued)]
        out += pair[::-1] if round_ % 2 else pair
    return out


def _ts(job: dict[str, Any], key: str) -> float:
    return dt.datetime.fromisoformat(job[key].replace("Z", "+00:00")).timestamp()


def run_phase(
    stack: ServiceStack,
    devices: list[str],
    shares: list[list[int]],
    archive: Path,
    params: dict[str, Any],
    jobs: int,
    uploaders: int = 1,
    queued: bool = False,
    upload_processes: bool = False,
) -> dict[str, Any]:
    """Start one worker per device (each warmed up, on a GPU), push ``jobs`` jobs from ``uploaders`` clients at
    once, wait for all; stop the workers. The phase's timings.

    ``queued``: the workers are paused (SIGSTOP to each worker's process group) while the jobs are uploaded and
    resumed together once all are queued; the phase's time runs from the resume, so it measures the workers alone,
    without the uploads sharing the host's CPUs (``uploads_seconds`` says how long those took).

    ``upload_processes``: each client is a process of its own (started before the phase's clock), not a thread of
    this one: on the 4 x H200 host the threads' multipart encoding, under this process's GIL, took about 1 GB/s
    in all whether 4 or 8 of them uploaded, less than four workers take."""
    workers = [start_worker(stack, i, dev, shares[i]) for i, dev in enumerate(devices)]
    for w, dev in zip(workers, devices, strict=True):
        warm = _warms_up(stack, dev)
        wait_until(lambda w=w, warm=warm: _ready(w, warm), 300, f"{w.name} to be ready", interval=0.2)
    if queued:
        for w in workers:
            w.signal_group(signal.SIGSTOP)

    # one client per thread, or per process (started, its imports done, before the clock starts)
    pool: Executor = (
        ProcessPoolExecutor(uploaders, mp_context=multiprocessing.get_context("spawn"))
        if upload_processes
        else ThreadPoolExecutor(uploaders)
    )
    upload = functools.partial(_post, stack.base_url, archive, params)
    try:
        with pool:  # clients upload side by side, as many users would
            if upload_processes:
                list(pool.map(time.sleep, [0.5] * uploaders))
            t0 = posting = time.time()
            posts = list(pool.map(upload, range(jobs)))
        if queued:
            t0 = time.time()
            for w in workers:
                w.signal_group(signal.SIGCONT)
        ids = [i for i, _, _ in posts]
        with stack.client(timeout=600) as client:
            done = [wait_for_job(client, i, stack=stack, timeout=3600, interval=0.2) for i in ids]
            wall_end = time.time()
    finally:
        for w in workers:
            w.signal_group(signal.SIGCONT)  # a paused worker would not see the SIGTERM
            w.stop(grace=10)
        stack.workers = [w for w in stack.workers if w not in workers]
    failed = [j for j in done if j["state"] != "succeeded"]
    if failed:
        raise RuntimeError(f"{len(failed)} job(s) did not succeed: {json.dumps(failed[0])[:2000]}")
    end = max(_ts(j, "finished_at") for j in done)
    job_seconds = [_ts(j, "finished_at") - _ts(j, "started_at") for j in done]
    detail = _jobs_detail(stack, done, posts, workers, t0)
    with stack.client(timeout=600) as client:  # measured: deleted, as retention would, so the data folder (often
        for i in ids:  # tmpfs) holds one phase's uploads and files at most, not every phase's
            assert client.delete(f"/v1/jobs/{i}").status_code == 204, i
    return {
        "workers": len(devices),
        "devices": devices,
        "cpus_per_worker": [len(s) for s in shares[: len(devices)]],
        "jobs": jobs,
        "uploaders": uploaders,
        "upload_processes": upload_processes,
        "seconds": end - t0,
        "client_seconds": wall_end - t0,
        "jobs_per_minute": 60 * jobs / (end - t0),
        "job_seconds": job_seconds,
        "mean_job_seconds": sum(job_seconds) / len(job_seconds),
        "most_jobs_running_at_once": _most_at_once(done),
        "first_start_seconds": min(_ts(j, "started_at") for j in done) - t0,
        "last_upload_done_seconds": max(e for _, _, e in posts) - t0,
        "queued": queued,
        "uploads_seconds": max(e for _, _, e in posts) - posting,
        "jobs_detail": detail,
        "after_first_jobs_per_minute": _after_first(detail, len(devices)),
        "stage_medians": _stage_medians(detail),
        "load_average_at_end": list(os.getloadavg()),
    }


def _report_seconds(client: Any, job: dict[str, Any]) -> dict[str, float]:
    """The engine's own seconds from the job's ``report.json``: each pipeline stage (``stage_seconds``) and the
    files' writing (``write_seconds``' totals), keyed ``pipeline.<stage>`` and ``files.<part>``; empty if absent."""
    url = next((o["url"] for o in job.get("outputs") or [] if o["name"] == "report.json"), None)
    resp = client.get(url) if url else None
    if resp is None or resp.status_code != 200:
        return {}
    report = resp.json()
    seconds = {f"pipeline.{k}": v for k, v in (report.get("stage_seconds") or {}).items()}
    if _is_number(report.get("finish_seconds")):  # the mesh's counts: the sync point after the stages
        seconds["pipeline.finish"] = report["finish_seconds"]
    seconds.update({f"files.{k}": v for k, v in (report.get("write_seconds") or {}).items() if _is_number(v)})
    return seconds


def _is_number(value: Any) -> bool:
    """A number (``write_seconds`` also holds a dict per file)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def _jobs_detail(
    stack: ServiceStack,
    done: list[dict[str, Any]],
    posts: list[tuple[str, float, float]],
    workers: list[Proc],
    t0: float,
) -> list[dict[str, Any]]:
    """One row per job, in the order they started: its worker (index in the phase), the client's POST time, when
    it started and ended (seconds from the first POST, server clock), the worker's seconds per step (``timings``,
    ``worker.tasks``), the engine's per stage (``engine``, from the job's report.json) and the API's per step of the
    upload (``api``: body, commit, inspect, decoder, ...; empty where its log has no line for the job)."""
    uploads = {i: (s, e) for i, s, e in posts}
    timings = worker_timings(workers)
    api = api_timings(stack)  # the API's seconds per step of each upload (service.intake's line)
    rows = []
    with stack.client(timeout=60) as client:
        for j in sorted(done, key=lambda j: _ts(j, "started_at")):
            index, steps = timings.get(j["id"], (None, {}))
            start, end = uploads[j["id"]]
            row = {"id": j["id"], "worker": index, "upload_seconds": end - start, "upload_done_at": end - t0}
            row.update(started_at=_ts(j, "started_at") - t0, finished_at=_ts(j, "finished_at") - t0)
            rows.append({**row, "timings": steps, "engine": _report_seconds(client, j), "api": api.get(j["id"], {})})
    return rows


def _after_first(detail: list[dict[str, Any]], workers: int) -> float | None:
    """Jobs per minute once every one of the phase's ``workers`` has finished its first job: the sum over the
    workers of (jobs after its first) / (its last finish - its first finish). Without the phase's start (the first
    uploads, a fresh worker's first job) and its tail (one worker idle while the other ends), this is the rate
    long-running workers keep; None where a worker ran fewer than 2 jobs (or none: another took its share)."""
    ends: dict[Any, list[float]] = {}
    for row in detail:
        ends.setdefault(row["worker"], []).append(row["finished_at"])
    if len(ends) < workers or not ends or min(len(e) for e in ends.values()) < 2:
        return None
    return sum(60 * (len(e) - 1) / (max(e) - min(e)) for e in ends.values())


def _stage_medians(detail: list[dict[str, Any]]) -> dict[str, float]:
    """The median seconds of each step over the jobs (the client's upload, the worker's, the engine's and the API's,
    ``api.<step>``)."""
    values: dict[str, list[float]] = {"upload": [r["upload_seconds"] for r in detail]}
    for row in detail:
        api = {f"api.{k}": v for k, v in row.get("api", {}).items()}
        for step, seconds in {**row["timings"], **row["engine"], **api}.items():
            values.setdefault(step, []).append(seconds)
    return {step: statistics.median(v) for step, v in values.items()}


def _most_at_once(jobs: list[dict[str, Any]]) -> int:
    """The most jobs that ran at the same time (from their started_at/finished_at): the workers really overlapped."""
    events = sorted([(_ts(j, "started_at"), 1) for j in jobs] + [(_ts(j, "finished_at"), -1) for j in jobs])
    running = most = 0
    for _, step in events:
        running += step
        most = max(most, running)
    return most


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--devices", default="cpu,cpu", help="one worker per entry: cpu, cuda:0, cuda:1, ...")
    parser.add_argument("--jobs", type=int, default=6, help="jobs per phase")
    parser.add_argument(
        "--rounds", type=int, default=1, help="rounds of the phases, one worker first in even rounds, all first in odd"
    )
    parser.add_argument("--input", type=Path, default=None, help="scan archive (default: the bundled CT head)")
    parser.add_argument("--params", default=None, help="job params JSON for --input")
    parser.add_argument("--phantom", default=None, help="instead of --input: the bone phantom of this shape Z,Y,X")
    parser.add_argument("--uploaders", type=int, default=2, help="clients uploading the jobs side by side (default 2)")
    parser.add_argument(
        "--upload-processes",
        action="store_true",
        help="each uploading client in a process of its own (default: threads of this one, about 1 GB/s in all)",
    )
    parser.add_argument("--api-workers", type=int, default=2, help="API processes (bonemesh serve --workers)")
    parser.add_argument(
        "--front-cpus",
        default="0",
        help="CPUs kept for the API, Redis and the upload clients, off the workers' (auto: 4 on 16+ CPUs; 0: none)",
    )
    parser.add_argument(
        "--mode",
        default="uploading",
        choices=("uploading", "queued", "both"),
        help="uploading: the jobs are uploaded while the workers run (end to end on one host); queued: all are "
        "queued first, the workers paused, and timed from their resume (the workers alone); both: one then the other",
    )
    parser.add_argument(
        "--cpu-layout",
        default="blocks",
        choices=("blocks", "halves"),
        help="workers' CPU shares: blocks (0-15, 16-31) or halves (0-7+16-23, 8-15+24-31)",
    )
    parser.add_argument(
        "--png-decoder", default="auto", choices=("auto", "libpng", "pillow"), help="the workers' BONEMESH_PNG_DECODER"
    )
    parser.add_argument(
        "--warmup", default="auto", choices=("auto", "true", "false"), help="the workers' BONEMESH_WARMUP"
    )
    parser.add_argument(
        "--warmup-volume-bytes",
        default="scan",
        help="the workers' BONEMESH_WARMUP_VOLUME_BYTES (scan: the phantom's volume with --phantom, as a worker set "
        "for its usual scans has; else the worker's default)",
    )
    parser.add_argument("--redis-server", default=None)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--warp-cache", type=Path, default=None, help="the workers' Warp kernel cache (default: new)")
    parser.add_argument("--machine", default=platform.node(), help="label of this machine in the JSON")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

    devices = [d.strip() for d in args.devices.split(",") if d.strip()]
    if len(devices) < 2:
        parser.error("--devices needs at least two entries (one worker per entry)")
    archive = args.input or HEADSQ_ZIP
    params = json.loads(args.params) if args.params else {"iso": 1150, "spacing": list(HEADSQ_SPACING_ZYX_MM)}
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bonemesh-throughput-"))
    workdir.mkdir(parents=True, exist_ok=True)
    prep: dict[str, Any] | None = None
    if args.phantom:
        from benchmarks.phantom_zip import PHANTOM_SPACING_MM, write_phantom_zip

        shape = tuple(int(v) for v in args.phantom.split(","))
        archive = workdir / f"phantom_{'x'.join(map(str, shape))}.zip"
        prep = write_phantom_zip(shape, archive)  # type: ignore[arg-type]
        params = {"iso": prep["iso"], "spacing": PHANTOM_SPACING_MM}
    reserve = args.warmup_volume_bytes
    if reserve == "scan":  # the phantom's 16-bit volume
        reserve = str(2 * shape[0] * shape[1] * shape[2]) if args.phantom else None
    front, back = split_front(args.front_cpus)
    shares = cpu_shares(len(devices), back, args.cpu_layout)
    if front:  # the API processes and Redis (started below) and the upload threads inherit it; workers use taskset
        os.sched_setaffinity(0, front)
    extra = {  # the Warp cache is shared, filled by the warm-up
        "WARP_CACHE_PATH": str(args.warp_cache or workdir / "warp-cache"),
        "BONEMESH_PNG_DECODER": args.png_decoder,
        "BONEMESH_WARMUP": args.warmup,
        **({"BONEMESH_WARMUP_VOLUME_BYTES": reserve} if reserve else {}),
    }
    report: dict[str, Any] = {
        "benchmark": "throughput",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": args.machine,
        "host": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "input": {"archive": archive.name, "bytes": archive.stat().st_size, "params": params, "preparation": prep},
        "timing": "first POST (queued phases: the workers' resume) to the last job's finished_at (server clock), "
        "all jobs posted at once by --uploaders clients, after a warm-up job and with each phase's workers warmed up",
        "ideal": len(devices),
        "front_cpus": front,
        "cpu_layout": args.cpu_layout,
        "png_decoder": args.png_decoder,
        "workers_warm_up": args.warmup,
        "warmup_volume_bytes": reserve or "default",
    }

    def write() -> None:
        write_json(args.out, report)

    stop_on_sigterm()  # `timeout`: the with-blocks below stop every process
    with (
        RedisServer(workdir / "redis", args.redis_server) as redis,
        ServiceStack(
            workdir / "stack",
            redis.url,
            stale_seconds=600,
            max_upload_bytes=archive.stat().st_size + (64 << 20),
            extra_env=extra,
        ) as stack,
    ):
        stack.start_server(workers=args.api_workers)
        report["api_processes"] = args.api_workers
        try:
            print(f"[throughput] warm-up on {devices[0]} (kernel compilation)", flush=True)
            report["warmup"] = run_phase(stack, devices[:1], shares, archive, params, 1)
            print(f"  {report['warmup']['seconds']:.1f} s", flush=True)
            for round_ in range(args.rounds):  # round 0's phases at the top level, later ones under more_rounds
                into = report if round_ == 0 else {}
                if round_:
                    report.setdefault("more_rounds", []).append(into)
                for key, devs, queued in _phases(args.mode, devices, round_):
                    how = "queued" if queued else "uploading"
                    where = f"{len(devs)} worker(s): {devs}, CPUs {shares}"
                    print(f"[throughput] round {round_}: {args.jobs} jobs ({how}) on {where}", flush=True)
                    phase = run_phase(
                        stack, devs, shares, archive, params, args.jobs, args.uploaders, queued, args.upload_processes
                    )
                    print(
                        f"  {phase['seconds']:.1f} s, {phase['jobs_per_minute']:.2f} jobs/min, mean job "
                        f"{phase['mean_job_seconds']:.1f} s, at most {phase['most_jobs_running_at_once']} at once",
                        flush=True,
                    )
                    medians = ", ".join(f"{k} {v:.2f}" for k, v in phase["stage_medians"].items())
                    print(f"  median seconds: {medians}", flush=True)
                    into[key] = phase
                    write()
        except BaseException:
            print(stack.logs(8000), file=sys.stderr)
            write()
            raise
    for prefix in ("", "queued_"):
        one_key, all_key = f"{prefix}one_worker", f"{prefix}all_workers"
        rounds = [report, *report.get("more_rounds", [])]  # a round cut short has one of its phases at most
        pairs = [(r[one_key], r[all_key]) for r in rounds if one_key in r and all_key in r]
        if not pairs:
            continue
        ratios = [one["seconds"] / all_["seconds"] for one, all_ in pairs]
        report[f"{prefix}speedup"] = ratios[0]
        report[f"{prefix}speedups"] = ratios
        report[f"{prefix}median_speedup"] = statistics.median(ratios)
        shown = ", ".join(f"{r:.2f}x" for r in ratios)
        print(f"[throughput] {prefix}speedup {shown} with {len(devices)} workers", flush=True)
        after_ratios = [
            all_["after_first_jobs_per_minute"] / one["after_first_jobs_per_minute"]
            for one, all_ in pairs
            if one["after_first_jobs_per_minute"] and all_["after_first_jobs_per_minute"]
        ]
        if after_ratios:
            report[f"{prefix}after_first_speedups"] = after_ratios
            shown = ", ".join(f"{r:.2f}x" for r in after_ratios)
            print(f"[throughput] {prefix}after each worker's first job {shown}", flush=True)
    write()
    print(f"[throughput] wrote {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
