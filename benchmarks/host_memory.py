"""Peak host memory of a whole job (``run_job``: load, mesh, files) under a host memory bound (issue 46), against the
bound and against the same job with the scan loaded whole.

    python -m benchmarks.host_memory [--shape 256,256,256] [--stack 12] [--bound 96MiB] [--formats npy,bigtiff,...]
                                     [--chunks 64,256,256] [--threads N] [--workdir DIR]
                                     [--device cuda:0 --device-bytes 4GiB] --out result.json

The bone phantom (uint16, ``engine.data.phantom.bone_phantom``) stacked ``--stack`` times along z, every other copy
mirrored (12 x 256 x 256 x 256 is 384 MiB, 4x the default bound; a phantom that long has finer bone, whose block
layers need more device memory than half the bound) is written once per format: ``npy``, ``tiff-folder`` (one TIFF per
slice), ``bigtiff`` (one file, a page per slice) and ``ome-zarr`` (v0.5, chunks ``--chunks``). Each is then meshed
twice on Warp's CPU device, each time in a new Python process that first imports the engine and its readers, resolves
the runtime and warms the device up on a small job (its kernels loaded), then notes its resident size (``baseline``,
VmRSS) and resets its high-water mark (``/proc/self/clear_refs``), runs the job and notes the peak (VmHWM;
``ru_maxrss`` where the mark cannot be reset):

The model keeps ``--reduction`` (0.05) of its faces: the decimated groups of slabs and the finished model are held
on the host (at the default 0.2 this phantom's model, 2.2 M faces, needs 149 MiB to finish on the CPU device alone).

* ``bounded``: ``--max-host-bytes`` the bound (the scan is read slab by slab from disk; the device budget on the
  CPU is half the bound);
* ``whole``: no host bound, the same device budget (the scan loaded whole, then streamed in the same slabs).

Reported per format and run: the peak, the baseline, ``used_bytes`` (peak - baseline: what the job cost), its ratio
to the bound, the seconds, the mesh's measures (faces, pieces, Euler characteristic) and the model's SHA-256;
``same_mesh``: the bounded run's model.stl is byte for byte the whole run's.

Measured here (2 CPUs, 12 x 256 x 256 x 256 uint16, 384 MiB, 96 MiB bound; ``benchmarks/results/host_memory_cpu.json``,
docs/host-memory.md): the same model bounded and whole from every format; the job 264-323 MiB over the baseline
bounded against 647-672 MiB whole (the scan saved); through the isosurface stage 41-57 MiB (114 MiB OME-Zarr), within
the bound; the peak is the decimated groups' finish on the host and the files, the same in both runs.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.big_formats import SPACING, write_format
from benchmarks.report import proc_status, stop_on_sigterm, write_json

FORMATS = ("npy", "tiff-folder", "bigtiff", "ome-zarr")
READERS = {"tiff-folder": ("tifffile",), "bigtiff": ("tifffile",), "ome-zarr": ("zarr",)}
WRITTEN_AS = {"npy": "npy", "tiff-folder": "tiff-folder", "bigtiff": "bigtiff", "ome-zarr": "ome-zarr-v05"}


def _reset_peak() -> bool:
    """Reset the resident set's high-water mark (Linux: ``5`` to ``/proc/self/clear_refs``); False where it cannot."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return proc_status("VmHWM") <= proc_status("VmRSS") + (1 << 20)


def _child(args: argparse.Namespace) -> dict[str, Any]:
    """In the measured process: import, warm up, note the baseline, run the job, note the peak."""
    import dataclasses
    import importlib

    for reader in READERS.get(args.child_format, ()):  # the format's reader, imported before the baseline
        importlib.import_module(reader)

    from engine.budget import Budget
    from engine.job import resolve_runtime, run_job
    from engine.job.spec import JobSpec
    from engine.job.warmup import warm_up
    from engine.params import DecimateParams

    budget = Budget(bytes=args.child_device_bytes, host_volume_share=args.volume_share)
    if args.child_bound:
        budget = budget.with_host(args.child_bound)
    runtime = resolve_runtime(args.device, budget, decode_threads=args.threads)
    warm_up(runtime)
    spec = JobSpec()
    spacing = None if args.child_format == "ome-zarr" else SPACING
    spec = dataclasses.replace(
        spec,
        input=dataclasses.replace(spec.input, spacing_zyx_mm=spacing),
        # the phantom reads as HU + 1024: no body outline out of core; the model decimated to a size the bound holds
        recon=dataclasses.replace(spec.recon, body=None, decimate=DecimateParams(reduction=args.reduction)),
    )
    baseline = proc_status("VmRSS")
    resettable = _reset_peak()
    stage, peaks, done = ["loading"], {}, threading.Event()

    def sample() -> None:  # the resident set over the baseline, per stage of the job (every 50 ms)
        while not done.is_set():
            used = proc_status("VmRSS") - baseline
            peaks[stage[0]] = max(peaks.get(stage[0], 0), used)
            time.sleep(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    result = run_job(
        args.child_input, args.child_outdir, spec, runtime, on_progress=lambda s, f: stage.__setitem__(0, s)
    )
    seconds = time.perf_counter() - t0
    done.set()
    sampler.join()
    peak = proc_status("VmHWM") if resettable else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    mesh = result.report["mesh"]
    stl = Path(args.child_outdir) / "model.stl"
    return {
        "peak_rss_bytes": peak,
        "baseline_rss_bytes": baseline,
        "peak_from": "VmHWM (reset after warm-up)" if resettable else "ru_maxrss",
        "seconds": round(seconds, 3),
        "stage_seconds": {k: round(v, 3) for k, v in result.report["stage_seconds"].items()},
        "stage_used_bytes": peaks,  # sampled: the peak resident set over the baseline while each stage ran
        "device_budget_bytes": runtime.budget.bytes,
        "host_bound_bytes": runtime.budget.host_bytes,
        "out_of_core": bool(result.report["memory"].get("out_of_core", False)),
        "faces": mesh["n_faces"],
        "mesh": {k: mesh[k] for k in ("n_faces", "n_vertices", "components", "euler", "watertight") if k in mesh},
        "model_stl_sha256": hashlib.sha256(stl.read_bytes()).hexdigest(),
    }


def _write(fmt: str, volume: np.ndarray, work: Path, chunks: tuple[int, int, int]) -> Path:
    """``volume`` written as ``fmt`` under ``work`` (``benchmarks.big_formats``' writers); the path to read."""
    return Path(write_format(WRITTEN_AS[fmt], volume, work, chunks, None))


def _measure(fmt: str, path: Path, outdir: Path, bound: int | None, device: int, args: argparse.Namespace) -> Any:
    argv = [sys.executable, "-m", "benchmarks.host_memory", "--out", str(args.out), "--child-format", fmt]
    argv += ["--child-input", str(path), "--child-outdir", str(outdir), "--child-device-bytes", str(device)]
    argv += ["--volume-share", str(args.volume_share), "--reduction", str(args.reduction), "--device", args.device]
    if bound is not None:
        argv += ["--child-bound", str(bound)]
    if args.threads:
        argv += ["--threads", str(args.threads)]
    repo = Path(__file__).resolve().parents[1]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=3600, check=False, cwd=repo)
    if done.returncode:
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1][:500]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run(args: argparse.Namespace, say: Callable[[str], None]) -> dict[str, Any]:
    from engine.budget import Budget, parse_bytes
    from engine.data.phantom import bone_phantom

    shape = tuple(int(v) for v in args.shape.split(","))
    chunks = [int(c) for c in args.chunks.split(",")]
    bound = parse_bytes(args.bound)
    assert bound is not None
    on_cpu = args.device == "cpu"
    # the device budget: on the CPU the bound's share of it; on a GPU its own (the bound holds the host's side)
    device = int(bound * Budget().host_device_share) if on_cpu else parse_bytes(args.device_bytes)
    assert device is not None
    wanted = [f.strip() for f in args.formats.split(",")] if args.formats else list(FORMATS)
    unknown = sorted(set(wanted) - set(FORMATS))
    if unknown:
        raise SystemExit(f"unknown format(s) {unknown}; choose from {', '.join(FORMATS)}")
    one = bone_phantom(shape, workers=args.threads)  # type: ignore[arg-type]
    volume = np.concatenate([one if k % 2 == 0 else one[::-1] for k in range(args.stack)])
    del one
    shape = volume.shape
    chunk_zyx = tuple(min(c, n) for c, n in zip(chunks, shape, strict=True))
    report: dict[str, Any] = {
        "benchmark": "host_memory",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "device": args.device,
        "shape_zyx": list(shape),
        "dtype": str(volume.dtype),
        "volume_bytes": int(volume.nbytes),
        "host_bound_bytes": bound,
        "volume_over_bound": round(volume.nbytes / bound, 3),
        "device_budget_bytes": device,
        "stacked": args.stack,
        "zarr_chunks": list(chunk_zyx),
        "threads": args.threads,
        "reduction": args.reduction,
        "formats": {},
    }
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bonemesh-host-memory-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        for fmt in wanted:
            fmt_work = work / fmt
            fmt_work.mkdir()
            path = _write(fmt, volume, fmt_work, chunk_zyx)  # type: ignore[arg-type]
            row: dict[str, Any] = {}
            for name, host in (("bounded", bound), ("whole", None)):
                r = _measure(fmt, path, fmt_work / f"out_{name}", host, device, args)
                if "error" not in r:
                    r["used_bytes"] = r["peak_rss_bytes"] - r["baseline_rss_bytes"]
                    r["used_over_bound"] = round(r["used_bytes"] / bound, 3)
                    say(
                        f"[host_memory] {fmt} {name}: used {r['used_bytes'] / 2**20:.0f} MiB "
                        f"({r['used_over_bound']:.2f}x the bound), {r['seconds']:.1f} s, {r['faces']:,} faces"
                    )
                else:
                    say(f"[host_memory] {fmt} {name}: {r['error']}")
                row[name] = r
            ok = all("error" not in row[k] for k in ("bounded", "whole"))
            row["same_mesh"] = ok and row["bounded"]["model_stl_sha256"] == row["whole"]["model_stl_sha256"]
            row["within_bound"] = ok and row["bounded"]["used_bytes"] <= bound
            report["formats"][fmt] = row
            shutil.rmtree(fmt_work, ignore_errors=True)
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shape", default="256,256,256", help="the phantom's shape Z,Y,X (uint16)")
    parser.add_argument("--stack", type=int, default=12, help="copies of the phantom stacked along z")
    parser.add_argument("--bound", default="96MiB", help="the host memory bound (--max-host-bytes)")
    parser.add_argument("--formats", default=None, help=f"comma-separated, default all: {','.join(FORMATS)}")
    parser.add_argument("--chunks", default="64,256,256", help="OME-Zarr chunk shape Z,Y,X")
    parser.add_argument(
        "--volume-share", type=float, default=0.5, help="a scan up to this share of the bound is loaded whole (tests)"
    )
    parser.add_argument(
        "--reduction", type=float, default=0.05, help="the share of the faces the model keeps (--reduction)"
    )
    parser.add_argument("--threads", type=int, default=None, help="decode threads (default: the CPUs)")
    parser.add_argument("--device", default="cpu", help="the job's device (cpu, cuda:0, opencl:0)")
    parser.add_argument(
        "--device-bytes", default="4GiB", help="the device budget on a GPU (on the CPU: the bound's share)"
    )
    parser.add_argument("--workdir", type=Path, default=None, help="where the files go (default: a temporary one)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--child-format", help=argparse.SUPPRESS)
    parser.add_argument("--child-input", help=argparse.SUPPRESS)
    parser.add_argument("--child-outdir", help=argparse.SUPPRESS)
    parser.add_argument("--child-bound", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-device-bytes", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_format is not None:  # the measured process: its result as JSON on stdout's last line
        print(json.dumps(_child(args)))
        return 0
    stop_on_sigterm()
    write_json(args.out, run(args, print))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
