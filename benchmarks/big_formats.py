"""Peak host memory of loading one volume from each big-volume format, against the volume's own bytes.

    python -m benchmarks.big_formats [--shape 768,512,512] [--formats npy,tiff-folder,...] [--threads N]
                                     [--chunks 64,256,256] [--workdir DIR] [--engine-root DIR] --out result.json

The bone phantom (uint16, ``engine.data.phantom.bone_phantom``) is written once per format: ``npy`` (the
reference), ``tiff-folder`` (one TIFF per slice), ``multipage-tiff`` (classic TIFF, under 4 GB), ``bigtiff``,
``ome-zarr-v04`` (Zarr v2), ``ome-zarr-v05`` (Zarr v3), ``ome-zarr-v05-sharded``, ``ome-zarr-v05-zip`` (the v0.5
folder in a stored zip) and ``ome-zarr-s3`` (the v0.5 folder in a SeaweedFS bucket on loopback,
``tests/service/seaweed.py``; read with the project's S3 variables). Each is then loaded by ``engine.io.load_volume``
in a new Python process, which first imports the readers (numpy, zarr, tifffile, obstore, ``engine.io``) and notes
its resident size (``baseline``), then loads and notes its peak (``VmHWM`` in ``/proc/self/status``, the high-water
mark of its resident set) before checking the volume against the reference. Reported per format: the peak, the
baseline, ``loaded_bytes`` (peak - baseline: what loading cost) and ``ratio`` (that over the volume's bytes; 1.0 is
the volume itself), the seconds and ``equal``. ``--engine-root`` measures another checkout's ``engine`` (e.g.
``git archive HEAD~1 engine | tar -x -C /tmp/old``) with this script.

Measured here (2 CPUs, 768 x 512 x 512 uint16, 384 MiB; ``benchmarks/results/big_formats_cpu*.json``), loading
over the baseline against the volume: before issue 46 (``--engine-root`` on the previous commit) multi-page TIFF and
BigTIFF 2.00x (the file's bytes read, then decoded into a second array), the TIFF folder 1.06x, OME-Zarr refused.
After: ``.npy`` 1.00x, multi-page TIFF and BigTIFF 1.01x, the TIFF folder 1.06x, OME-Zarr v0.5 1.17x (folder),
1.14x (zip), 1.18x (S3), v0.4 (Zarr v2) 1.34x, v0.5 sharded (128 MiB shards) 1.46x. The OME-Zarr excess is the
chunks in flight, the same at twice the size (1536 x 512 x 512: +51 MiB on v3, +123 MiB on v2, +201 MiB sharded,
``big_formats_cpu_768mib.json``), so it fades against a 100 GB volume.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.report import proc_status, stop_on_sigterm, write_json

FORMATS = (
    "npy",
    "tiff-folder",
    "multipage-tiff",
    "bigtiff",
    "ome-zarr-v04",
    "ome-zarr-v05",
    "ome-zarr-v05-sharded",
    "ome-zarr-v05-zip",
    "ome-zarr-s3",
)
SPACING = (0.05, 0.05, 0.05)  # mm, for the formats that do not carry it (OME-Zarr's metadata say 50 micrometer)


def _child(args: argparse.Namespace) -> dict[str, Any]:
    """In the measured process: import the readers, note the baseline, load, note the peak, then check."""
    if args.engine_root:
        sys.path.insert(0, str(args.engine_root))
    import numcodecs  # noqa: F401  # the readers, imported before the baseline like the engine's own
    import tifffile  # noqa: F401
    import zarr  # noqa: F401

    try:
        import obstore  # noqa: F401
    except ImportError:
        pass
    from engine.io import load_volume

    baseline = proc_status("VmRSS")
    zarr_input = args.child_format.startswith("ome-zarr")
    t0 = time.perf_counter()
    volume = load_volume(args.child_input, spacing_zyx_mm=None if zarr_input else SPACING, threads=args.threads)
    seconds = time.perf_counter() - t0
    peak = proc_status("VmHWM")
    ref = np.load(args.child_reference, mmap_mode="r")
    equal = volume.data.shape == ref.shape and all(
        np.array_equal(volume.data[z : z + 16], ref[z : z + 16]) for z in range(0, ref.shape[0], 16)
    )
    return {
        "peak_rss_bytes": peak,
        "baseline_rss_bytes": baseline,
        "seconds": seconds,
        "equal": bool(equal),
        "spacing_zyx_mm": list(volume.spacing_zyx_mm),
        "source": {k: v for k, v in volume.source.items() if k != "completeness"},
    }


def _write_tiffs(fmt: str, volume: np.ndarray, work: Path) -> Path:
    import tifffile

    if fmt == "tiff-folder":
        folder = work / "slices"
        folder.mkdir()
        for k, plane in enumerate(volume):
            tifffile.imwrite(folder / f"slice_{k:05d}.tif", plane)
        return folder
    path = work / f"{fmt}.tif"
    tifffile.imwrite(path, volume, bigtiff=fmt == "bigtiff")
    return path


def write_format(fmt: str, volume: np.ndarray, work: Path, chunks: tuple[int, int, int], s3: Any) -> Path | str:
    """``volume`` written as ``fmt`` under ``work``; the path (or URL) to load."""
    from tests.engine.omezarr_factory import upload_folder, write_ome_zarr, zip_folder

    if fmt == "npy":
        np.save(work / "volume.npy", volume)
        return work / "volume.npy"
    if fmt in ("tiff-folder", "multipage-tiff", "bigtiff"):
        return _write_tiffs(fmt, volume, work)
    um = [s * 1000 for s in SPACING]
    if fmt in ("ome-zarr-v04", "ome-zarr-v05", "ome-zarr-v05-sharded"):
        version = "0.4" if fmt.endswith("v04") else "0.5"
        shards = tuple(min(4 * c, n) for c, n in zip(chunks, volume.shape, strict=True)) if "sharded" in fmt else None
        return write_ome_zarr(work / f"{fmt}.ome.zarr", volume, version=version, scale=um, chunks=chunks, shards=shards)
    folder = write_ome_zarr(work / "scan.ome.zarr", volume, version="0.5", scale=um, chunks=chunks)
    if fmt == "ome-zarr-v05-zip":
        path = zip_folder(folder, work / "scan.ome.zarr.zip")
        shutil.rmtree(folder)
        return path
    bucket = s3.make_bucket()
    url = upload_folder(s3.client(), folder, bucket, "scans/scan.ome.zarr")
    shutil.rmtree(folder)
    return url


def _stored_bytes(path: Path | str) -> int | None:
    if isinstance(path, str):
        return None
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _measure(
    fmt: str, path: Path | str, reference: Path, args: argparse.Namespace, env: dict[str, str]
) -> dict[str, Any]:
    argv = [sys.executable, "-m", "benchmarks.big_formats", "--out", str(args.out), "--child-format", fmt]
    argv += ["--child-input", str(path), "--child-reference", str(reference)]
    if args.threads:
        argv += ["--threads", str(args.threads)]
    if args.engine_root:
        argv += ["--engine-root", str(args.engine_root)]
    repo = Path(__file__).resolve().parents[1]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=1800, check=False, env=env, cwd=repo)
    if done.returncode:
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1][:500]}
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def _seaweed(wanted: list[str]) -> Any:
    """A SeaweedFS server when ``ome-zarr-s3`` is wanted (None otherwise)."""
    if "ome-zarr-s3" not in wanted:
        return None
    from tests.service.seaweed import SeaweedServer

    return SeaweedServer()


def _row(fmt: str, result: dict[str, Any], stored: int | None, volume_bytes: int) -> dict[str, Any]:
    if "error" in result:
        return result
    loaded = result["peak_rss_bytes"] - result["baseline_rss_bytes"]
    return {**result, "stored_bytes": stored, "loaded_bytes": loaded, "ratio": round(loaded / volume_bytes, 4)}


def run(args: argparse.Namespace, say: Callable[[str], None]) -> dict[str, Any]:
    from engine.data.phantom import bone_phantom

    shape = tuple(int(v) for v in args.shape.split(","))
    chunks = tuple(int(v) for v in args.chunks.split(","))
    wanted = [f.strip() for f in args.formats.split(",")] if args.formats else list(FORMATS)
    unknown = sorted(set(wanted) - set(FORMATS))
    if unknown:
        raise SystemExit(f"unknown format(s) {unknown}; choose from {', '.join(FORMATS)}")
    volume = bone_phantom(shape, workers=args.threads)  # type: ignore[arg-type]
    volume_bytes = int(volume.nbytes)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bonemesh-big-formats-"))
    work.mkdir(parents=True, exist_ok=True)
    reference = work / "reference.npy"
    np.save(reference, volume)
    report: dict[str, Any] = {
        "benchmark": "big_formats",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "engine_root": str(args.engine_root) if args.engine_root else None,
        "shape_zyx": list(shape),
        "dtype": str(volume.dtype),
        "volume_bytes": volume_bytes,
        "zarr_chunks": list(chunks),
        "threads": args.threads,
        "formats": {},
    }
    s3 = _seaweed(wanted)
    try:
        env = {**os.environ}
        if s3 is not None:
            env.update({k: v for k, v in s3.env("unused").items() if k != "BONEMESH_STORAGE_URL"})
        for fmt in wanted:
            if fmt == "multipage-tiff" and volume_bytes >= 4 << 30:
                report["formats"][fmt] = {"skipped": "a classic TIFF holds at most 4 GB"}
                continue
            fmt_work = work / fmt
            fmt_work.mkdir()
            path = write_format(fmt, volume, fmt_work, chunks, s3)
            row = _row(fmt, _measure(fmt, path, reference, args, env), _stored_bytes(path), volume_bytes)
            report["formats"][fmt] = row
            shutil.rmtree(fmt_work, ignore_errors=True)
            if "error" in row:
                say(f"[big_formats] {fmt}: {row['error']}")
            else:
                mib = row["peak_rss_bytes"] / 2**20, row["loaded_bytes"] / 2**20
                say(f"[big_formats] {fmt}: peak {mib[0]:.0f} MiB, loading {mib[1]:.0f} MiB = {row['ratio']:.2f}x")
    finally:
        if s3 is not None:
            s3.close()
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shape", default="768,512,512", help="the phantom's shape Z,Y,X (uint16)")
    parser.add_argument("--formats", default=None, help=f"comma-separated, default all: {','.join(FORMATS)}")
    parser.add_argument("--chunks", default="64,256,256", help="OME-Zarr chunk shape Z,Y,X (shards: 4x that)")
    parser.add_argument("--threads", type=int, default=None, help="decode threads (default: the CPUs)")
    parser.add_argument("--workdir", type=Path, default=None, help="where the files go (default: a temporary one)")
    parser.add_argument("--engine-root", type=Path, default=None, help="measure the engine package under this dir")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--child-format", help=argparse.SUPPRESS)
    parser.add_argument("--child-input", help=argparse.SUPPRESS)
    parser.add_argument("--child-reference", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_format is not None:  # the measured process: its result as JSON on stdout's last line
        print(json.dumps(_child(args)))
        return 0
    stop_on_sigterm()
    write_json(args.out, run(args, print))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
