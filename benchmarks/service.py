"""Service benchmark: upload-to-links latency of the web service, per stage, with real processes.

    python -m benchmarks.service --device cpu|cuda:0 [--data ../shared/data] [--phantom Z,Y,X] [--repeat N]
                                 [--baseline] [--predecode on|off] [--predecode-process on|off]
                                 [--predecode-anchor] [--upload-mbps MB/s]
                                 [--redis-server PATH] [--timeout S] [--workdir DIR] --out result.json

It starts a redis-server on a free loopback port, ``bonemesh serve`` and one ``bonemesh worker`` (device
``--device``) with a fresh data folder (the helpers of ``tests/service/procs.py``), then for each input POSTs the
archive and polls ``GET /v1/jobs/{id}`` every 0.1 s until the job has succeeded and its links are out. One
warm-up job (the bundled headsq scan) runs first, so Warp's kernel compilation is not counted.

Inputs: the cranium CT (PNG zip of HU + 1024, bone preset via ``hu_offset``) when the data folder holds it, and a
slice archive of the bone phantom of ``benchmarks.phantom`` (952 x 1024 x 1024 by default, as in the issue; a zip
of 16-bit PNG slices written beforehand and not timed).

Per run it records, from the client's side: the upload (POST until 202), the wait in the queue (created_at to
started_at), the job (started_at to finished_at) and upload-to-links (POST start until the first GET that shows
the succeeded job with its links); the time the client first saw each stage (loading, the pipeline's stages,
writing); and from ``report.json`` the pipeline's own stage seconds and counts. A run that does not finish within
``--timeout`` is recorded with the stage it had reached. The JSON is rewritten after every input, so a run cut
short still leaves what it measured.

``--baseline`` adds, in the same run, each input once (``--baseline-repeat``) through a second worker on the
ingest path of the commits before issue 11's ingest work: one decoding thread (``BONEMESH_DECODE_THREADS=1``) and
every PNG through Pillow (``BONEMESH_PNG_DECODER=pillow``), with its own warm-up job (the API restarted beside it
without decoding during the upload, ``BONEMESH_DECODE_DURING_UPLOAD=false``). Everything else (the
pipeline on the GPU, the one-pass writers) is today's in both, so the difference is the ingest change alone; the
older pipeline and writers are not runnable in this build (their numbers are in the committed JSON of earlier
runs: ``benchmarks/results/service_cuda.json``).

Issue 46 item 4: a zip of PNG slices is decoded while it is uploaded (``BONEMESH_DECODE_DURING_UPLOAD``,
``engine.io.predecode``), so the worker's loading phase reads the decoded volume instead. ``--predecode on|off``
sets it for the main runs; ``--predecode-anchor`` adds, in the same run, each input ``--repeat`` times with it
switched the other way (the API and the worker restarted with the setting, warmed up again): the anchor of the
comparison (``results.<input>.predecode_anchor``, and ``predecode_effect``: the median upload, loading phase and
upload-to-links seconds both ways). Each run also records the worker's own seconds per step (its ``job <id>
timings`` log line: ``load`` is the loading phase on the worker's clock, not the client's 0.1 s polling) and
whether the report says the slices were ``decoded_during_upload``. ``--upload-mbps`` sends each input's upload no
faster than that (a client's link rather than loopback), so that the decoding can hide behind it.
``--predecode-process on|off`` (``BONEMESH_PREDECODE_PROCESS``, default on as the setting's default): the API
decodes in a child process of its own (``engine.io.predecode_proc``) or on threads of the API process.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

from benchmarks.phantom_zip import PHANTOM_SPACING_MM, write_phantom_zip
from benchmarks.report import stop_on_sigterm, write_json
from benchmarks.timing_lines import api_timings, worker_timings
from tests.service.procs import RedisServer, ServiceStack

UPLOAD_RATE: list[float | None] = [None]  # --upload-mbps, in bytes a second (the inputs' uploads, not the warm-ups)
PREDECODE = "BONEMESH_DECODE_DURING_UPLOAD"
BASELINE_ENV = {"BONEMESH_DECODE_THREADS": "1", "BONEMESH_PNG_DECODER": "pillow", PREDECODE: "false"}
BASELINE = (
    "the ingest path before issue 11: one decoding thread, every PNG through Pillow (and no decoding during the "
    "upload: the API restarted without it)"
)
CRANIUM = (
    "cranium_ct",
    "cranium_ct_png16.zip",
    {"preset": "bone", "hu_offset": 1024, "spacing": [1.5, 0.9570312, 0.9570312]},
)


class _Paced:
    """A file read no faster than ``rate`` bytes a second (a client's network link, ``--upload-mbps``)."""

    def __init__(self, fh: Any, rate: float) -> None:
        self.fh, self.rate, self.sent, self.t0 = fh, rate, 0, time.perf_counter()

    def read(self, n: int = -1) -> bytes:
        data = self.fh.read(min(n, 1 << 20) if n and n > 0 else 1 << 20)
        self.sent += len(data)
        ahead = self.sent / self.rate - (time.perf_counter() - self.t0)
        if ahead > 0:
            time.sleep(ahead)
        return bytes(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.fh, name)


def run_job(
    base_url: str,
    key: str,
    archive: Path,
    params: dict[str, Any],
    timeout: float,
    label: str,
    upload_rate: float | None = None,
) -> dict[str, Any]:
    """Upload (at most ``upload_rate`` bytes a second, where given), poll to the links; the timings of one job."""
    stages_seen: dict[str, float] = {}
    with httpx.Client(base_url=base_url, headers={"X-API-Key": key}, timeout=3600) as client:
        t0 = time.perf_counter()
        with open(archive, "rb") as raw:
            fh: Any = raw if upload_rate is None else _Paced(raw, upload_rate)
            resp = client.post(
                "/v1/jobs",
                files={"file": (archive.name, fh, "application/zip")},
                data={"params": json.dumps(params)},
            )
        upload_s = time.perf_counter() - t0
        if resp.status_code != 202:
            return {"label": label, "error": f"POST -> {resp.status_code}: {resp.text[:1000]}"}
        job_id = resp.json()["id"]
        job: dict[str, Any] = resp.json()
        last_print = 0.0
        while True:
            now = time.perf_counter() - t0
            job = client.get(f"/v1/jobs/{job_id}").json()
            stage = job.get("stage") or job["state"]
            if job["state"] == "running" and stage not in stages_seen:
                stages_seen[stage] = now
                print(f"    {now:8.2f} s  {stage} ({job['progress']:.0f} %)", flush=True)
            if job["state"] in ("succeeded", "failed", "cancelled"):
                break
            if now > timeout:
                return {
                    "label": label,
                    "job_id": job_id,
                    "error": f"not finished after {timeout:.0f} s",
                    "last_seen": job,
                    "upload_seconds": upload_s,
                    "stages_first_seen_seconds": stages_seen,
                }
            if now - last_print > 30:
                last_print = now
                print(f"    {now:8.2f} s  ... {job['state']} {stage} {job['progress']:.0f} %", flush=True)
            time.sleep(0.1)
        links_s = time.perf_counter() - t0
        if job["state"] != "succeeded":
            return {"label": label, "job_id": job_id, "error": job.get("error"), "state": job["state"]}
        outputs = {o["name"]: o for o in job["outputs"]}
        report = httpx.get(outputs["report.json"]["url"], timeout=60).json()

    pipeline_first = [t for s, t in stages_seen.items() if s not in ("starting", "loading", "writing", "done")]
    phases = {}  # client-side, to the 0.1 s polling step
    if "loading" in stages_seen and pipeline_first:
        phases["loading"] = min(pipeline_first) - stages_seen["loading"]
    if "writing" in stages_seen:
        phases["writing"] = links_s - stages_seen["writing"]

    def ts(key: str) -> float:
        return dt.datetime.fromisoformat(job[key].replace("Z", "+00:00")).timestamp()

    return {
        "label": label,
        "job_id": job_id,
        "upload_bytes": archive.stat().st_size,
        "upload_seconds": upload_s,
        "queue_seconds": ts("started_at") - ts("created_at"),
        "job_seconds": ts("finished_at") - ts("started_at"),
        "upload_to_links_seconds": links_s,
        "attempts": job["attempts"],
        "stages_first_seen_seconds": stages_seen,
        "phase_seconds": phases,
        "pipeline_stage_seconds": report["stage_seconds"],
        "pipeline_seconds": report["total_seconds"],
        "input": report["input"],
        "decoded_during_upload": bool(report["input"].get("source", {}).get("decoded_during_upload")),
        "counts": report["counts"],
        "mesh_faces": report["mesh"]["n_faces"],
        "outputs": {n: {"bytes": o["bytes"], "triangles": o["triangles"]} for n, o in outputs.items()},
        "device": report["device"],
    }


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"runs": runs}
    ok.sort(key=lambda r: r["upload_to_links_seconds"])
    median = ok[len(ok) // 2]
    return {
        "upload_to_links_seconds": median["upload_to_links_seconds"],
        "upload_to_links_seconds_all": [r["upload_to_links_seconds"] for r in runs if "error" not in r],
        "median_run": median,
        "runs_all": ok,
        "failed_runs": [r for r in runs if "error" in r],
        "median_upload_to_links_spread": statistics.pstdev(r["upload_to_links_seconds"] for r in ok),
    }


def _run_inputs(
    stack: ServiceStack, inputs: dict[str, tuple[Path, dict[str, Any]]], repeat: int, timeout: float, tag: str
) -> Iterator[tuple[str, dict[str, Any]]]:
    """Each input ``repeat`` times through the running worker: (name, summary) as each input is done."""
    for name, (path, params) in inputs.items():
        runs = []
        for i in range(repeat):
            print(f"[service] {tag}{name} run {i + 1}/{repeat} ({path.stat().st_size:,} bytes)", flush=True)
            run = run_job(stack.base_url, "key-a", path, params, timeout, f"{tag}{name}#{i + 1}", UPLOAD_RATE[0])
            if "job_id" in run:
                time.sleep(0.2)  # the worker writes its timing line as the attempt ends
                run["worker_seconds"] = worker_timings(stack.workers).get(run["job_id"], (0, {}))[1]
                run["api_upload_seconds"] = api_timings(stack).get(run["job_id"], {})
            runs.append(run)
            if "error" in run:
                print(f"  FAILED: {run['error']}", flush=True)
                break
            stages = ", ".join(f"{k} {v:.2f}" for k, v in run["pipeline_stage_seconds"].items())
            print(
                f"  upload {run['upload_seconds']:.2f} s, queue {run['queue_seconds']:.2f} s, job"
                f" {run['job_seconds']:.2f} s, upload-to-links {run['upload_to_links_seconds']:.2f} s"
                f" (loading/writing {run['phase_seconds']}, worker load {run['worker_seconds'].get('load')}, "
                f"decoded during the upload: {run['decoded_during_upload']}; pipeline: {stages})",
                flush=True,
            )
        yield name, _summary(runs)


def _warm_up(stack: ServiceStack, tag: str) -> dict[str, Any]:
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

    print(f"[service] {tag}warm-up: headsq (kernel compilation, Warp's modules loaded in the worker)", flush=True)
    params = {"iso": 1150, "spacing": list(HEADSQ_SPACING_ZYX_MM)}
    warm = run_job(stack.base_url, "key-a", HEADSQ_ZIP, params, 600, f"{tag}warmup")
    print(f"  warm-up {warm.get('upload_to_links_seconds', warm.get('error'))}", flush=True)
    return warm


def _restart(stack: ServiceStack, env: dict[str, str]) -> None:
    """The API and the worker stopped and started again with ``env`` (same data, queue and Redis)."""
    for proc in [*stack.workers, *stack.servers]:
        proc.stop(grace=10)
    stack.workers.clear()
    stack.servers.clear()
    stack.base_url = ""
    stack.start_server(extra_env=env)
    stack.start_worker(extra_env=env)


def _effect(on: dict[str, Any], off: dict[str, Any]) -> dict[str, Any]:
    """The medians of upload, loading phase and upload-to-links seconds with and without decoding during the
    upload."""
    picks = {
        "upload_seconds": lambda r: r.get("upload_seconds"),
        "loading_seconds_client": lambda r: r.get("phase_seconds", {}).get("loading"),
        "loading_seconds_worker": lambda r: r.get("worker_seconds", {}).get("load"),
        "upload_to_links_seconds": lambda r: r.get("upload_to_links_seconds"),
    }
    out: dict[str, Any] = {}
    for key, pick in picks.items():
        a = [float(v) for r in on.get("runs_all", []) if isinstance(v := pick(r), int | float)]
        b = [float(v) for r in off.get("runs_all", []) if isinstance(v := pick(r), int | float)]
        out[key] = {
            "with": statistics.median(a) if a else None,
            "without": statistics.median(b) if b else None,
        }
    return out


def _failed(results: dict[str, Any]) -> bool:
    return any("error" in r for res in results.values() for r in res.get("failed_runs", res.get("runs", [])))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="the worker's BONEMESH_DEVICE: cpu, cuda:0, auto")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--phantom", default="952,1024,1024", help="phantom shape Z,Y,X; 'none' to skip")
    parser.add_argument("--repeat", type=int, default=1, help="runs per input (the median is reported)")
    parser.add_argument("--baseline", action="store_true", help="also run the inputs on the previous ingest path")
    parser.add_argument("--baseline-repeat", type=int, default=1, help="baseline runs per input")
    parser.add_argument(
        "--predecode",
        choices=("on", "off"),
        default="on",
        help="BONEMESH_DECODE_DURING_UPLOAD of the main runs (slices decoded while uploaded)",
    )
    parser.add_argument(
        "--predecode-process",
        choices=("on", "off"),
        default="on",
        help="BONEMESH_PREDECODE_PROCESS: the API decodes in a child process (on) or on its own threads (off)",
    )
    parser.add_argument(
        "--predecode-min-bytes",
        type=int,
        default=None,
        help="BONEMESH_PREDECODE_MIN_BYTES of the runs: the smallest upload decoded while it arrives (default: the "
        "setting's, 64 MiB: the cranium is left to the worker; 0: every upload)",
    )
    parser.add_argument(
        "--predecode-anchor",
        action="store_true",
        help="also run each input with decoding during the upload switched the other way",
    )
    parser.add_argument(
        "--upload-mbps", type=float, default=None, help="send each input's upload at most this fast (MB/s): a link"
    )
    parser.add_argument("--redis-server", default=None, help="redis-server executable (default: PATH or apt-get)")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds one job may take before giving up")
    parser.add_argument("--workdir", type=Path, default=None, help="data, logs and archives (default: a temp dir)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bonemesh-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    inputs: dict[str, tuple[Path, dict[str, Any]]] = {}
    prep: dict[str, Any] = {}
    cranium = args.data / CRANIUM[0] / CRANIUM[1]
    if cranium.exists():
        inputs["cranium_ct"] = (cranium, CRANIUM[2])
    else:
        print(f"[service] {cranium} is absent: no cranium run", flush=True)
    if args.phantom.lower() != "none":
        shape = tuple(int(s) for s in args.phantom.split(","))
        name = f"phantom_{'x'.join(map(str, shape))}"
        path = workdir / f"{name}.zip"
        print(f"[service] writing the {shape} phantom archive to {path}", flush=True)
        prep[name] = write_phantom_zip(shape, path)  # type: ignore[arg-type]
        print(f"  {prep[name]}", flush=True)
        inputs[name] = (path, {"iso": prep[name]["iso"], "spacing": PHANTOM_SPACING_MM})

    results: dict[str, Any] = {}
    report: dict[str, Any] = {
        "benchmark": "service",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "device": args.device,
        "host": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "timing": (
            f"median of {args.repeat} per input after one warm-up job; client-side times from POST start; "
            "pipeline stage seconds from report.json of the median run"
        ),
        "preparation": prep,
        "results": results,
    }
    if args.baseline:
        report["baseline"] = {"what": BASELINE, "worker_env": BASELINE_ENV, "runs_per_input": args.baseline_repeat}
    UPLOAD_RATE[0] = args.upload_mbps * 1e6 if args.upload_mbps else None
    main_env = {
        PREDECODE: "true" if args.predecode == "on" else "false",
        "BONEMESH_PREDECODE_PROCESS": "true" if args.predecode_process == "on" else "false",
    }
    if args.predecode_min_bytes is not None:
        main_env["BONEMESH_PREDECODE_MIN_BYTES"] = str(args.predecode_min_bytes)
    report["predecode"] = {
        "main_runs": args.predecode,
        "process": args.predecode_process,
        "env": main_env,
        "upload_mbps": args.upload_mbps,
    }

    def write() -> None:
        write_json(args.out, report)

    stop_on_sigterm()  # `timeout`: the with-blocks below stop every process
    with (
        RedisServer(workdir / "redis", args.redis_server) as redis,
        ServiceStack(
            workdir / "stack",
            redis.url,
            device=args.device,
            stale_seconds=120,
            reconcile_seconds=15,
            max_upload_bytes=16 << 30,
            extra_env={
                "BONEMESH_JOB_SOFT_TIME_LIMIT": str(int(args.timeout)),
                "BONEMESH_JOB_TIME_LIMIT": str(int(args.timeout) + 60),
                **main_env,
            },
        ) as stack,
    ):
        stack.start_server()
        stack.start_worker()
        try:
            report["warmup"] = _warm_up(stack, "")
            for name, summary in _run_inputs(stack, inputs, args.repeat, args.timeout, ""):
                results[name] = summary
                write()
            if args.predecode_anchor:  # the same inputs, the setting the other way (issue 46 item 4's anchor)
                other = {PREDECODE: "false" if args.predecode == "on" else "true"}
                report["predecode"]["anchor_env"] = other
                _restart(stack, other)
                report["predecode"]["anchor_warmup"] = _warm_up(stack, "predecode anchor ")
                for name, summary in _run_inputs(stack, inputs, args.repeat, args.timeout, "predecode anchor "):
                    results[name]["predecode_anchor"] = summary
                    on, off = (results[name], summary) if args.predecode == "on" else (summary, results[name])
                    results[name]["predecode_effect"] = effect = _effect(on, off)
                    print(f"  {name}: with / without decoding during the upload: {effect}", flush=True)
                    write()
                _restart(stack, main_env)
            if args.baseline:  # the same queue and data; the API and a worker on the old ingest path
                _restart(stack, BASELINE_ENV)
                report["baseline"]["warmup"] = _warm_up(stack, "baseline ")
                for name, summary in _run_inputs(stack, inputs, args.baseline_repeat, args.timeout, "baseline "):
                    results[name]["baseline"] = summary
                    new, old = results[name].get("upload_to_links_seconds"), summary.get("upload_to_links_seconds")
                    if new and old:
                        results[name]["baseline_over_new"] = old / new
                        print(f"  {name}: upload-to-links {new:.2f} s, baseline {old:.2f} s ({old / new:.2f}x)")
                    write()
        except BaseException:
            print(stack.logs(20000), file=sys.stderr)
            write()
            raise
        if _failed(results) or any(_failed({"b": r["baseline"]}) for r in results.values() if "baseline" in r):
            print(stack.logs(20000), file=sys.stderr)
    write()
    print(f"[service] wrote {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
