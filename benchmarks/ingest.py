"""Ingest benchmark: a slice archive into a volume (and onto the device), serial against threaded (and, for
DICOM, against processes), with peak RSS.

    python -m benchmarks.ingest --shape 952,1024,1024 [--threads N] [--formats png,dicom] [--device cuda:0]
                                [--repeat 3] [--workdir DIR] --out benchmarks/results/ingest_<machine>.json

It writes the bone phantom of ``benchmarks.phantom`` as a zip of 16-bit PNG slices (``benchmarks.phantom_zip``,
stored, as the service benchmark uploads it) and, with ``dicom`` in ``--formats``, as a zip of
uncompressed single-frame CT DICOM files (HU + 1024 stored, rescale intercept -1024: the int16 in-place rescale).
Neither is timed. Then each measurement runs ``engine.io.load_volume`` in a fresh Python process, so its peak RSS
(``VmHWM``) is that load's alone:

- ``serial``: ``threads=1`` and the general decoders (imageio/Pillow), one slice after another on the calling
  thread: the path of the previous commits (the anchor, measured in the same run);
- ``threaded_pillow`` (PNG only): ``threads=N``, still the general decoders;
- ``threaded``: ``threads=N`` (default: every CPU of this process, ``engine.io.decode_threads``) with the fast PNG
  decoder (``engine.io.codecs``, imagecodecs) where it is installed: what ``load_volume`` does by default for
  slice images; for DICOM, N threads with ``processes=False``;
- ``processes`` (DICOM only): N worker processes (``engine.io.procs``), what ``load_volume`` does by default for a
  series of at least ``engine.io.dicom.PROCESS_MIN_FILES`` files. Each fresh process starts its fork server, so
  the time includes that start (a worker process pays it once, for its first DICOM job). The child records how
  many processes really ran (0 would mean it fell back to threads).

Each is the median of ``--repeat`` processes. With ``--device cuda:N`` the child also times the upload that makes
the volume device-ready, ``wp.array(volume)`` from pageable memory as ``engine.job.pipeline`` does, and the same
through a pinned host buffer (copy into it, then upload), so the lead can see whether pinning pays. No network.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def _rss_now() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_rss() -> int:
    """This process's peak resident set (VmHWM). Not ``getrusage``'s ru_maxrss: Linux carries that over fork and
    exec, so a child of a parent that held the phantom would report the parent's peak."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # not Linux: KiB on most systems


def _child(
    archive: Path, threads: int, spacing: list[float] | None, device: str | None, codec: str, processes: bool
) -> dict[str, Any]:
    """One load in this (fresh) process: seconds, peak RSS, a checksum of the array; optionally the upload."""
    import numpy as np

    from engine.io import codecs, dicom, load_volume, procs

    codecs.USE_IMAGECODECS = codec == "auto"
    ran: list[int] = []  # worker processes of each decode pool that ran (one given up at start is not closed)
    close = procs.DecodePool.close

    def counted_close(pool: procs.DecodePool) -> None:
        ran.append(len(pool.pool._processes or {}))  # type: ignore[attr-defined]
        close(pool)

    procs.DecodePool.close = counted_close  # type: ignore[method-assign]
    started: list[float] = []  # seconds until each pool's first worker answered (the fork server's start included)
    start_pool = dicom.start_pool

    @contextlib.contextmanager
    def timed_start(workers: int) -> Iterator[Any]:
        t = time.perf_counter()
        with start_pool(workers) as pool:
            started.append(time.perf_counter() - t)
            yield pool

    dicom.start_pool = timed_start  # type: ignore[assignment]

    rss_before = _rss_now()
    t0 = time.perf_counter()
    vol = load_volume(archive, spacing_zyx_mm=spacing, threads=threads, processes=processes)
    seconds = time.perf_counter() - t0
    peak = _peak_rss()
    data = vol.data
    out: dict[str, Any] = {
        "seconds": seconds,
        "threads": threads,
        "codec": codec,
        "processes_asked": processes,
        "decode_processes_ran": sum(ran),
        "decode_pool_start_seconds": sum(started),
        "imagecodecs_available": codecs._imagecodecs() is not None,
        "shape": list(data.shape),
        "dtype": str(data.dtype),
        "volume_bytes": int(data.nbytes),
        "rss_before_load_bytes": rss_before,
        "peak_rss_bytes": peak,
        "peak_rss_over_volume": peak / data.nbytes,
        "load_overhead_bytes": peak - rss_before - data.nbytes,
        "checksum": int(data.astype(np.int64).sum(dtype=np.int64)),
        "voxels_per_second": data.size / seconds,
    }
    if device:
        out["upload"] = _upload(data, device)
    return out


def _upload(data: Any, device: str) -> dict[str, Any]:
    """Host-to-device copy of the loaded volume from pageable memory and through a pinned buffer (Warp where it is
    installed, as the pipeline does; else CuPy, the same driver copy)."""
    import numpy as np

    try:
        import warp as wp
    except ImportError:
        return _upload_cupy(data, device)
    wp.init()
    with wp.ScopedDevice(device):
        wp.array(np.zeros(1 << 20, np.uint8))
        wp.synchronize()
        t0 = time.perf_counter()
        dev = wp.array(data)  # as engine.job.pipeline's upload stage does: from pageable memory
        wp.synchronize()
        pageable = time.perf_counter() - t0
        del dev
        t0 = time.perf_counter()
        pinned = wp.empty(data.shape, dtype=wp.dtype_from_numpy(data.dtype), device="cpu", pinned=True)
        alloc = time.perf_counter() - t0
        t0 = time.perf_counter()
        np.copyto(pinned.numpy(), data)
        copy = time.perf_counter() - t0
        t0 = time.perf_counter()
        dev = wp.clone(pinned, device=device)
        wp.synchronize()
        from_pinned = time.perf_counter() - t0
        del dev, pinned
    return _upload_report("warp", data.nbytes, pageable, alloc, copy, from_pinned)


def _upload_cupy(data: Any, device: str) -> dict[str, Any]:
    import cupy as cp
    import numpy as np

    with cp.cuda.Device(int(device.split(":")[1]) if ":" in device else 0):
        cp.zeros(1 << 20, np.uint8)
        cp.cuda.runtime.deviceSynchronize()
        t0 = time.perf_counter()
        dev = cp.asarray(data)
        cp.cuda.runtime.deviceSynchronize()
        pageable = time.perf_counter() - t0
        del dev
        t0 = time.perf_counter()
        mem = cp.cuda.alloc_pinned_memory(data.nbytes)
        pinned = np.frombuffer(mem, data.dtype, data.size).reshape(data.shape)
        alloc = time.perf_counter() - t0
        t0 = time.perf_counter()
        np.copyto(pinned, data)
        copy = time.perf_counter() - t0
        dev = cp.empty(data.shape, data.dtype)
        t0 = time.perf_counter()
        dev.set(pinned)
        cp.cuda.runtime.deviceSynchronize()
        from_pinned = time.perf_counter() - t0
        del dev, pinned, mem
    return _upload_report("cupy", data.nbytes, pageable, alloc, copy, from_pinned)


def _upload_report(
    via: str, nbytes: int, pageable: float, alloc: float, copy: float, from_pinned: float
) -> dict[str, Any]:
    gb = nbytes / 1e9
    return {
        "via": via,
        "pageable_seconds": pageable,
        "pageable_gb_per_s": gb / pageable,
        "pinned_alloc_seconds": alloc,
        "pinned_copy_in_seconds": copy,
        "pinned_upload_seconds": from_pinned,
        "pinned_gb_per_s": gb / from_pinned,
        "note": "decoding straight into a pinned buffer would skip the copy-in; engine.io takes no allocator yet",
    }


def _measure(
    archive: Path, threads: int, spacing: list[float] | None, device: str | None, codec: str, processes: bool
) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)}
    argv = [sys.executable, "-m", "benchmarks.ingest", "--child", str(archive), "--threads", str(threads)]
    argv += ["--codec", codec] + (["--processes"] if processes else [])
    if spacing:
        argv += ["--spacing", ",".join(map(str, spacing))]
    if device:
        argv += ["--device", device]
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=REPO, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed ({proc.returncode}):\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def write_dicom_zip(shape: tuple[int, int, int], path: Path, spacing_mm: list[float]) -> dict[str, Any]:
    """The phantom as a zip of uncompressed CT DICOM slices (stored values HU + 1024, intercept -1024)."""
    from pydicom.uid import generate_uid

    from benchmarks.phantom import bone_phantom
    from tests.engine.dicom_factory import ct_slice

    t0 = time.perf_counter()
    volume = bone_phantom(shape)
    uid = generate_uid()
    sz, sy, sx = spacing_mm
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for z, plane in enumerate(volume):
            data = ct_slice(plane, ipp=(0.0, 0.0, z * sz), pixel_spacing=(sy, sx), series_uid=uid, instance=z + 1)
            zf.writestr(f"dicom/IM{z + 1:05d}", data)
    return {"write_seconds": time.perf_counter() - t0, "archive_bytes": path.stat().st_size}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shape", default="952,1024,1024", help="phantom shape Z,Y,X")
    parser.add_argument("--threads", type=int, default=None, help="threaded run's threads (default: every CPU)")
    parser.add_argument("--formats", default="png,dicom", help="comma list of png, dicom")
    parser.add_argument("--device", default=None, help="also time the upload to this Warp device (cuda:0)")
    parser.add_argument("--repeat", type=int, default=3, help="processes per measurement (median reported)")
    parser.add_argument("--machine", default=platform.node(), help="label of this machine in the JSON")
    parser.add_argument("--workdir", type=Path, default=None, help="where the archives go (default: a temp dir)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--spacing", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--codec", default="auto", help=argparse.SUPPRESS)
    parser.add_argument("--processes", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    spacing_arg = [float(v) for v in args.spacing.split(",")] if args.spacing else None
    if args.child is not None:
        child = _child(args.child, args.threads or 1, spacing_arg, args.device, args.codec, args.processes)
        print(json.dumps(child))
        return 0
    if args.out is None:
        parser.error("--out is required")

    from benchmarks.phantom_zip import PHANTOM_SPACING_MM, write_phantom_zip
    from engine.io import decode_threads

    threads = decode_threads(args.threads)
    shape = tuple(int(s) for s in args.shape.split(","))
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bonemesh-ingest-"))
    workdir.mkdir(parents=True, exist_ok=True)
    tag = "x".join(map(str, shape))
    results: dict[str, Any] = {}
    for fmt in [f.strip() for f in args.formats.split(",") if f.strip()]:
        archive = workdir / f"phantom_{tag}_{fmt}.zip"
        print(f"[ingest] writing {archive}", flush=True)
        if fmt == "png":
            prep = write_phantom_zip(shape, archive)  # type: ignore[arg-type]
            spacing: list[float] | None = PHANTOM_SPACING_MM
        elif fmt == "dicom":
            prep = write_dicom_zip(shape, archive, PHANTOM_SPACING_MM)  # type: ignore[arg-type]
            spacing = None
        else:
            parser.error(f"unknown format {fmt!r}: expected png or dicom")
        modes = [("serial", 1, "pillow", False), ("threaded", threads, "auto", False)]
        if fmt == "png":  # the general (Pillow) decoder on threads too: what the fast PNG path adds
            modes.insert(1, ("threaded_pillow", threads, "pillow", False))
        elif threads > 1:  # pydicom's parse holds the GIL: processes
            modes.append(("processes", threads, "auto", True))
        runs: dict[str, list[dict[str, Any]]] = {mode: [] for mode, *_ in modes}
        for i in range(args.repeat):
            for mode, n, codec, in_procs in modes:
                run = _measure(archive, n, spacing, args.device if mode == "threaded" else None, codec, in_procs)
                runs[mode].append(run)
                print(
                    f"  {fmt} {mode:15s} #{i + 1}: {run['seconds']:.3f} s ({n} {'processes' if in_procs else 'threads'}"
                    f", {run['decode_processes_ran']} decode processes ran, started in"
                    f" {run['decode_pool_start_seconds']:.2f} s), peak RSS "
                    f"{run['peak_rss_bytes'] / 1e9:.2f} GB = {run['peak_rss_over_volume']:.2f}x the volume",
                    flush=True,
                )
        checks = {r["checksum"] for rs in runs.values() for r in rs}
        med = {mode: statistics.median(r["seconds"] for r in rs) for mode, rs in runs.items()}
        results[fmt] = {
            "archive": {"bytes": archive.stat().st_size, **prep},
            "serial_seconds": med["serial"],
            "threaded_seconds": med["threaded"],
            "threaded_pillow_seconds": med.get("threaded_pillow"),
            "processes_seconds": med.get("processes"),
            "speedup": med["serial"] / med["threaded"],
            "processes_speedup": med["serial"] / med["processes"] if "processes" in med else None,
            "threads": threads,
            "same_volume": len(checks) == 1,
            "peak_rss_over_volume": {m: max(r["peak_rss_over_volume"] for r in rs) for m, rs in runs.items()},
            "runs": runs,
        }
        in_procs_text = f", {threads} processes {med['processes']:.3f} s" if "processes" in med else ""
        print(
            f"[ingest] {fmt}: serial {med['serial']:.3f} s, {threads} threads {med['threaded']:.3f} s, "
            f"x{results[fmt]['speedup']:.2f}{in_procs_text}; same volume: {len(checks) == 1}",
            flush=True,
        )
        archive.unlink()
    report = {
        "benchmark": "ingest",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": args.machine,
        "host": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "cpus_usable": len(os.sched_getaffinity(0)),
            "python": platform.python_version(),
        },
        "shape": list(shape),
        "timing": f"median of {args.repeat} fresh processes per mode; load_volume() only (the archive on local disk)",
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"[ingest] wrote {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
