"""PNG slices unfiltered on the device against libpng on the host (``engine.io.png_rows``): a stack's load time,
its CPU seconds, and the device's own time for the rows.

    python -m benchmarks.png_rows [--phantom 476,1024,1024] [--encoders pillow,paeth] [--device cuda:0]
                                  [--threads N] [--slab-mb 64,256] [--loads 3] --out result.json

The bone phantom (``benchmarks.phantom``) is written as a zip of 16-bit PNG slices by each encoder: ``pillow``
(what ``benchmarks.phantom_zip`` uploads: Pillow at level 1, rows filtered None, Sub or Up) and ``paeth`` (every row
Paeth-filtered: the longest chain of the device's serial work, and the filter of 87 % of the rows of the real
512 x 512 scans of ``../shared``). Then, in this process, after a warm-up load each:

- ``host``: ``load_volume`` with libpng unfiltering on the decode threads (the anchor, in the same run);
- ``device_<N>mb``: the rows unfiltered on ``--device`` in slabs of N MB (``DeviceRows``, staging and volume in
  page-locked buffers where the device is CUDA, as a worker has them).

Each mode's ``--loads`` loads are timed with their user and system CPU seconds (``getrusage``: all threads). The
device modes' volumes are checked equal to the host's. ``device_only`` times the device's part alone for the whole
stack (rows already inflated): the copies and kernels of one slab the size of the stack.
"""

from __future__ import annotations

import argparse
import datetime as dt
import io
import platform
import resource
import statistics
import struct
import tempfile
import time
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.report import write_json

SPACING = (1.0, 1.0, 1.0)


def paeth_png(plane: np.ndarray) -> bytes:
    """A 16-bit grayscale PNG of ``plane`` with every row Paeth-filtered (zlib level 1)."""
    h, w = plane.shape
    raw = plane.astype(">u2").view(np.uint8).reshape(h, 2 * w).astype(np.int16)
    a = np.pad(raw, ((0, 0), (2, 0)))[:, :-2]  # the same byte of the sample to the left (0 at the edge)
    b = np.pad(raw, ((1, 0), (0, 0)))[:-1]  # above
    c = np.pad(b, ((0, 0), (2, 0)))[:, :-2]  # above left
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    pred = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
    rows = np.concatenate([np.full((h, 1), 4, np.uint8), ((raw - pred) % 256).astype(np.uint8)], axis=1)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
    stream = zlib.compress(rows.tobytes(), 1)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", stream) + chunk(b"IEND", b"")


def _encode(plane: np.ndarray, encoder: str) -> bytes:
    if encoder == "paeth":
        return paeth_png(plane)
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(plane).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def write_zip(volume: np.ndarray, encoder: str, path: Path) -> dict[str, Any]:
    """``volume`` as a stored zip of PNG slices by ``encoder``; its size and the share of each filter type."""
    from concurrent.futures import ThreadPoolExecutor

    from engine.io.codecs import inflate_rows

    kinds = np.zeros(5, np.int64)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf, ThreadPoolExecutor() as pool:
        for z, data in enumerate(pool.map(lambda p: _encode(p, encoder), volume)):
            zf.writestr(f"s/{z:04d}.png", data)
            if z % 16 == 0:  # a sample of slices' filter types
                rows = np.empty((volume.shape[1], 1 + volume.shape[2] * volume.itemsize), np.uint8)
                if inflate_rows(data, volume.shape[1:], volume.dtype, memoryview(rows.reshape(-1))):
                    kinds += np.bincount(rows[:, 0], minlength=5)[:5]
    return {"bytes": path.stat().st_size, "filter_share": [round(float(k / kinds.sum()), 3) for k in kinds]}


def _timed(fn: Any, n: int) -> list[dict[str, float]]:
    """``n`` timed calls of ``fn`` after a warm-up (page cache, imports, kernels, buffers); its results are dropped
    at once, so that the reused buffers are free for the next call."""
    fn()
    rows = []
    for _ in range(n):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        fn()
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        rows.append(
            {
                "seconds": round(time.perf_counter() - t0, 4),
                "user": round(r1.ru_utime - r0.ru_utime, 3),
                "sys": round(r1.ru_stime - r0.ru_stime, 3),
            }
        )
    return rows


def _summary(rows: list[dict[str, float]]) -> dict[str, Any]:
    return {
        "loads": rows,
        "median_seconds": statistics.median(r["seconds"] for r in rows),
        "median_cpu": statistics.median(r["user"] + r["sys"] for r in rows),
    }


def device_only(path: Path, device: str, threads: int) -> dict[str, Any]:
    """The device's part for the whole stack at once: rows inflated first (not timed), then one slab's copies and
    kernels, timed to the device's synchronisation (median of 3 after a warm-up), into the worker's reused volume
    buffer (page-locked on CUDA). The committed ``png_rows_2xh100.json`` came from a version that copied the samples
    into a fresh pageable array each time (its ``device_only`` includes touching 1 GB of new pages)."""
    from engine.backend.select import get_backend
    from engine.io import load_volume
    from engine.io.png_rows import DeviceRows
    from engine.staging import VolumeBuffer, pinned_rows, pinned_volumes

    allocate = pinned_volumes(device) or VolumeBuffer(pinned=False)
    rows = DeviceRows(get_backend(device), allocate=pinned_rows(device), slab_bytes=1 << 62)  # one slab, at the end
    sent: list[float] = []
    send = rows._send

    def timed_send(lo: int, hi: int) -> None:
        t0 = time.perf_counter()
        send(lo, hi)
        rows.backend.synchronize()
        sent.append(time.perf_counter() - t0)

    rows._send = timed_send  # type: ignore[method-assign]
    for _ in range(4):
        load_volume(path, spacing_zyx_mm=SPACING, threads=threads, allocate=allocate, rows=rows)
    return {"seconds": [round(s, 4) for s in sent[1:]], "median_seconds": round(statistics.median(sent[1:]), 4)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--phantom", default="476,1024,1024", help="z,y,x of the bone phantom")
    parser.add_argument(
        "--encoders", default="pillow,paeth", help="PNG encoders of the stacks, comma-separated: pillow, paeth"
    )
    parser.add_argument("--device", default="cuda:0", help="the device that unfilters (a GPU; cpu for a smoke run)")
    parser.add_argument("--threads", type=int, default=None, help="decode threads (default: this process's CPUs)")
    parser.add_argument("--slab-mb", default="64,256", help="slab sizes of the device modes, comma-separated (MB)")
    parser.add_argument("--loads", type=int, default=3, help="timed loads per mode")
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    from benchmarks.phantom import bone_phantom
    from engine.backend.select import get_backend
    from engine.io import load_volume
    from engine.io.parallel import decode_threads
    from engine.io.png_rows import DeviceRows
    from engine.staging import VolumeBuffer, pinned_rows, pinned_volumes

    shape = tuple(int(v) for v in args.phantom.split(","))
    threads = decode_threads(args.threads)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bonemesh-png-rows-"))
    workdir.mkdir(parents=True, exist_ok=True)
    backend = get_backend(args.device)
    report: dict[str, Any] = {
        "benchmark": "png_rows",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "python": platform.python_version()},
        "device": backend.label,
        "shape_zyx": list(shape),
        "threads": threads,
        "stacks": {},
    }
    volume = bone_phantom(shape)  # type: ignore[arg-type]
    allocate = pinned_volumes(args.device) or VolumeBuffer(pinned=False)  # the worker's buffer (CPU: reused too)
    for encoder in args.encoders.split(","):
        path = workdir / f"phantom_{encoder}.zip"
        entry: dict[str, Any] = {"zip": write_zip(volume, encoder, path)}

        def load(rows: DeviceRows | None, path: Path = path) -> np.ndarray:
            data: np.ndarray = load_volume(
                path, spacing_zyx_mm=SPACING, threads=threads, allocate=allocate, rows=rows
            ).data
            return data

        host = load(None).copy()
        entry["host"] = _summary(_timed(lambda: load(None), args.loads))
        for mb in [int(v) for v in args.slab_mb.split(",") if v]:
            rows = DeviceRows(backend, allocate=pinned_rows(args.device), slab_bytes=mb << 20)
            runs = _timed(lambda rows=rows: load(rows), args.loads)
            entry[f"device_{mb}mb"] = {**_summary(runs), "equal_to_host": bool(np.array_equal(load(rows), host))}
        del host
        entry["device_only"] = device_only(path, args.device, threads)
        host_row = entry["host"]
        for key, value in entry.items():
            if key.startswith("device_") and "median_seconds" in value and key != "device_only":
                value["seconds_ratio_to_host"] = round(value["median_seconds"] / host_row["median_seconds"], 3)
                value["cpu_ratio_to_host"] = round(value["median_cpu"] / max(host_row["median_cpu"], 1e-9), 3)
        report["stacks"][encoder] = entry
        print(f"[png_rows] {encoder}: {entry}", flush=True)
        write_json(args.out, report)
        path.unlink()


if __name__ == "__main__":
    main()
