"""Isosurface benchmark: our Marching Cubes 33 vs scikit-image (Lewiner) vs Warp's classic marching cubes.

    python -m benchmarks.mc33 --device cpu|cuda:0 --shape Z,Y,X --repeat N --out result.json
                              [--skip-skimage] [--skip-warp] [--skimage-crop auto|full|zslab|cube]
                              [--skimage-max-voxels N] [--warp-slab P] [--seed S]

The volume is ``benchmarks.phantom.bone_phantom(shape, seed)`` (uint16, HU + 1024), the level ``BONE_LEVEL``.
Every method is timed end to end from the same host numpy array to host numpy results (wall clock,
``time.perf_counter``): one warm-up run (Warp compiles/loads kernels on first use), then the median of N runs.

* ours: ``engine.isosurface.marching_cubes_33(vol, BONE_LEVEL, device=..., closed=False)``.
* skimage: ``skimage.measure.marching_cubes(vol, level, method="lewiner")`` on the host CPU, single-threaded (it
  converts the uint16 input to float32 itself). On CUDA runs it gets, by default, a central z-slab over the whole
  cross-section of at most 256^3 voxels (16 planes of 1024^2): a central 256^3 cube of the 1024^2 phantom lies
  entirely in the marrow cavity and has no surface. Its voxels/s are the crop's, and ours is also timed on the same
  crop (``ours_on_skimage_crop``) for a same-input ratio.
* warp_mc: Warp's ``warp.geometry.IsoSurfaceMarchingCubes.extract`` (``wp.MarchingCubes`` is a deprecated alias
  in Warp 1.19) on the same device: per z slab of ``--warp-slab`` cells (one plane overlap) the uint16 slab is
  converted to float32 on the host, uploaded, extracted and the mesh downloaded; counts are summed over slabs
  (vertices on the seams are counted once per slab).

Peak device memory on CUDA: the high-water mark of the CUDA default memory pool that Warp allocates from
(``wp.get_mempool_used_mem_high``), reset before each method through the driver API where possible; otherwise
the cumulative mark is reported and labelled so. The engine's own estimate (``stats.peak_slab_bytes``) is always
recorded too. On the CPU there is no device pool: the engine estimate and the process peak RSS are recorded.
"""

from __future__ import annotations

import argparse
import ctypes
import datetime as _dt
import json
import os
import platform
import resource
import statistics
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.phantom import BONE_LEVEL, bone_phantom

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SHAPE = {"cpu": (256, 256, 256), "cuda": (952, 1024, 1024)}
_CU_MEMPOOL_ATTR_USED_MEM_HIGH = 8  # cuda.h, enum CUmemPool_attribute


# ---------------------------------------------------------------------------------------------------- host info


def _say(msg: str = "", flush: bool = False) -> None:
    sys.stdout.write(msg + "\n")
    if flush:
        sys.stdout.flush()


def _cpu_model() -> str | None:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def _host_memory_bytes() -> int | None:
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _peak_rss_bytes() -> int:
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB


def _git_commit() -> str | None:
    """HEAD's commit read from .git (no git process); None when not a checkout."""
    git = REPO / ".git"
    try:
        if git.is_file():  # worktree: "gitdir: <path>"
            git = Path(git.read_text().split(":", 1)[1].strip())
        head = (git / "HEAD").read_text().strip()
        if not head.startswith("ref:"):
            return head
        ref = head.split(":", 1)[1].strip()
        common = git
        if (git / "commondir").is_file():
            common = (git / (git / "commondir").read_text().strip()).resolve()
        for base in (git, common):
            if (base / ref).is_file():
                return (base / ref).read_text().strip()
        for base in (git, common):
            packed = base / "packed-refs"
            if packed.is_file():
                for line in packed.read_text().splitlines():
                    parts = line.split()
                    if len(parts) == 2 and parts[1] == ref:
                        return parts[0]
    except (OSError, IndexError):
        pass
    return None


def _versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": platform.python_version(), "numpy": np.__version__}
    for name in ("warp", "skimage", "scipy"):
        try:
            mod = __import__(name)
            out[name] = getattr(mod, "__version__", None)
        except Exception:
            out[name] = None
    return out


# ------------------------------------------------------------------------------------------- device memory


def _reset_mempool_high(dev: Any) -> bool:
    """Reset the used-memory high-water mark of the device's default CUDA memory pool (driver API)."""
    try:
        lib = ctypes.CDLL("libcuda.so.1")
        lib.cuDeviceGet.argtypes = [ctypes.POINTER(ctypes.c_int), ctypes.c_int]
        lib.cuDeviceGetDefaultMemPool.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_int]
        lib.cuMemPoolSetAttribute.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
        cu_dev = ctypes.c_int()
        if lib.cuDeviceGet(ctypes.byref(cu_dev), int(dev.ordinal)) != 0:
            return False
        pool = ctypes.c_void_p()
        if lib.cuDeviceGetDefaultMemPool(ctypes.byref(pool), cu_dev) != 0:
            return False
        zero = ctypes.c_uint64(0)
        return lib.cuMemPoolSetAttribute(pool, _CU_MEMPOOL_ATTR_USED_MEM_HIGH, ctypes.byref(zero)) == 0
    except Exception:
        return False


class _DeviceMemory:
    """Peak device memory of one method: the Warp/CUDA mempool high-water mark where available."""

    def __init__(self, dev: Any) -> None:
        import warp as wp

        self.wp, self.dev = wp, dev
        self.reset_ok = False
        self.baseline = 0
        try:
            self.enabled = bool(dev.is_cuda and wp.is_mempool_enabled(dev))
        except Exception:
            self.enabled = False

    def start(self) -> None:
        if not self.enabled:
            return
        try:
            self.wp.synchronize_device(self.dev)
            self.reset_ok = _reset_mempool_high(self.dev)
            if self.reset_ok:
                # the mark restarts from the memory in use right now (tables, pool leftovers)
                self.baseline = int(self.wp.get_mempool_used_mem_current(self.dev))
                high = int(self.wp.get_mempool_used_mem_high(self.dev))
                self.reset_ok = high <= self.baseline + (1 << 20)
        except Exception:
            self.reset_ok = False

    def result(self) -> dict[str, Any]:
        try:
            return self._result()
        except Exception as exc:
            return {"peak_device_memory_bytes": None, "peak_device_memory_method": f"probe failed: {exc}"}

    def _result(self) -> dict[str, Any]:
        if not self.dev.is_cuda:
            return {
                "peak_device_memory_bytes": None,
                "peak_device_memory_method": "n/a on CPU (no device pool); see peak_host_rss_bytes",
            }
        if not self.enabled:
            return {
                "peak_device_memory_bytes": None,
                "peak_device_memory_method": "n/a: Warp memory pool not enabled on this device",
            }
        self.wp.synchronize_device(self.dev)
        high = int(self.wp.get_mempool_used_mem_high(self.dev))
        if self.reset_ok:
            how = (
                "CUDA default mempool used-memory high-water mark (wp.get_mempool_used_mem_high), reset before "
                "this method's warm-up; includes memory already in use at reset (in_use_at_reset_bytes)"
            )
            return {
                "peak_device_memory_bytes": high,
                "in_use_at_reset_bytes": self.baseline,
                "peak_device_memory_method": how,
            }
        how = (
            "CUDA default mempool used-memory high-water mark (wp.get_mempool_used_mem_high), CUMULATIVE over the "
            "process (could not reset it): an upper bound that includes earlier methods"
        )
        return {"peak_device_memory_bytes": high, "peak_device_memory_method": how}


# --------------------------------------------------------------------------------------------------- timing


def _timed(fn: Callable[[], tuple[int, int]], repeat: int, sync: Callable[[], None]) -> dict[str, Any]:
    """Warm-up once, then ``repeat`` timed runs; fn returns (vertices, triangles)."""
    sync()
    t0 = time.perf_counter()
    counts = fn()
    sync()
    warm = time.perf_counter() - t0
    secs = []
    for _ in range(repeat):
        sync()
        t0 = time.perf_counter()
        c = fn()
        sync()
        secs.append(time.perf_counter() - t0)
        if c != counts:
            raise RuntimeError(f"Expected the same counts on every run, got {counts} then {c}")
    return {
        "warmup_seconds": warm,
        "seconds_all": secs,
        "seconds": statistics.median(secs),
        "vertices": int(counts[0]),
        "triangles": int(counts[1]),
    }


def _bench_ours(
    vol: np.ndarray, dev_spec: str, dev: Any, repeat: int, sync: Callable[[], None], label: str = "full volume"
) -> dict[str, Any]:
    from engine.isosurface import IsosurfaceStats, marching_cubes_33

    last: dict[str, Any] = {}

    def run() -> tuple[int, int]:
        st = IsosurfaceStats()
        v, f = marching_cubes_33(vol, BONE_LEVEL, device=dev_spec, closed=False, stats=st)
        last["stats"] = st
        return int(v.shape[0]), int(f.shape[0])

    mem = _DeviceMemory(dev)
    mem.start()
    res = _timed(run, repeat, sync)
    st = last["stats"]
    res["stats"] = {
        "slabs": st.slabs,
        "blocks": st.blocks,
        "active_blocks": st.active_blocks,
        "table_misses": st.table_misses,
        "peak_slab_bytes": st.peak_slab_bytes,
        "slab_layers": list(st.slab_layers),
    }
    res.update(mem.result())
    res["peak_device_memory_engine_estimate_bytes"] = st.peak_slab_bytes
    res["input"] = label
    res["shape"] = list(vol.shape)
    res["voxels"] = int(vol.size)
    res["call"] = f"marching_cubes_33(vol, {BONE_LEVEL}, device={dev_spec!r}, closed=False)"
    return res


def _bench_ours_resident(vol: np.ndarray, dev: Any, repeat: int, sync: Callable[[], None]) -> dict[str, Any]:
    """The engine on a volume already on the device, mesh left on the device (the pipeline's situation)."""
    import warp as wp

    from engine.isosurface import IsosurfaceStats, extract_isosurface

    field = wp.array(vol, device=dev)

    def run() -> tuple[int, int]:
        v, f = extract_isosurface(field, BONE_LEVEL, closed=False)
        return int(v.shape[0]), int(f.shape[0])

    mem = _DeviceMemory(dev)
    mem.start()
    res = _timed(run, repeat, sync)
    res.update(mem.result())
    prof = IsosurfaceStats(profile=True)
    extract_isosurface(field, BONE_LEVEL, closed=False, stats=prof)
    res["stage_seconds_profiled_run"] = prof.timings
    res["stats"] = {"slabs": prof.slabs, "blocks": prof.blocks, "active_blocks": prof.active_blocks}
    res["input"] = "full volume, uint16 already on the device; mesh stays on the device"
    res["voxels"] = int(vol.size)
    res["call"] = f"extract_isosurface(wp.array(vol), {BONE_LEVEL}, closed=False)"
    return res


def _bench_warp_resident(vol: np.ndarray, dev: Any, repeat: int, slab: int, sync: Callable[[], None]) -> dict[str, Any]:
    """Warp's classic marching cubes on float32 slabs already on the device, mesh left on the device."""
    import warp as wp

    extract, api = _warp_mc_extract()
    nz = vol.shape[0]
    cap = max(1, (2**31 - 1) // (3 * vol.shape[1] * vol.shape[2]) - 1)
    cells = max(1, min(int(slab), cap))
    fields = [
        wp.array(vol[z0 : min(z0 + cells, nz - 1) + 1].astype(np.float32), device=dev) for z0 in range(0, nz - 1, cells)
    ]

    def run() -> tuple[int, int]:
        nv = nt = 0
        for field in fields:
            verts, idx = extract(field, float(BONE_LEVEL))
            nv += int(verts.shape[0])
            nt += int(idx.shape[0] // 3)
        return nv, nt

    res = _timed(run, repeat, sync)
    res["input"] = f"full volume as {len(fields)} float32 slabs already on the device; mesh stays on the device"
    res["api"] = api
    res["voxels"] = int(vol.size)
    return res


def _crop(vol: np.ndarray, mode: str, max_voxels: int) -> np.ndarray:
    """The skimage input: the full volume, a central cube, or a central z-slab over the whole cross-section."""
    if mode == "full" or vol.size <= max_voxels:
        return vol
    if mode == "cube":
        side = max(2, round(max_voxels ** (1.0 / 3.0)))
        sl = []
        for n in vol.shape:
            m = min(n, side)
            sl.append(slice((n - m) // 2, (n - m) // 2 + m))
        return np.ascontiguousarray(vol[tuple(sl)])
    if mode == "zslab":
        planes = max(2, min(vol.shape[0], max_voxels // (vol.shape[1] * vol.shape[2])))
        z0 = (vol.shape[0] - planes) // 2
        return np.ascontiguousarray(vol[z0 : z0 + planes])
    raise ValueError(f"Expected crop mode full, cube or zslab, got {mode!r}")


def _bench_skimage(sub: np.ndarray, full_shape: tuple[int, ...], repeat: int, mode: str) -> dict[str, Any]:
    from skimage.measure import marching_cubes

    def run() -> tuple[int, int]:
        v, f, _n, _val = marching_cubes(sub, BONE_LEVEL, method="lewiner")
        return int(v.shape[0]), int(f.shape[0])

    res = _timed(run, repeat, lambda: None)
    res["shape"] = list(sub.shape)
    res["voxels"] = int(sub.size)
    res["input"] = (
        "full volume"
        if tuple(sub.shape) == tuple(full_shape)
        else f"crop '{mode}' {tuple(sub.shape)} of the volume (voxels/s are the crop's)"
    )
    res["call"] = f"skimage.measure.marching_cubes(vol_{sub.dtype}, {BONE_LEVEL}, method='lewiner') (host CPU)"
    return res


def _warp_mc_extract() -> tuple[Callable[[Any, float], tuple[Any, Any]], str]:
    """Warp's classic marching cubes: the 1.18+ API, or the old wp.MarchingCubes object."""
    import warp as wp

    try:
        import warp.geometry as wg

        cls = wg.IsoSurfaceMarchingCubes

        def extract(field: Any, threshold: float) -> tuple[Any, Any]:
            return cls.extract(field, threshold)

        return extract, "warp.geometry.IsoSurfaceMarchingCubes.extract(field, threshold)"
    except (ImportError, AttributeError):
        pass

    def extract_old(field: Any, threshold: float) -> tuple[Any, Any]:  # Warp <= 1.17
        nx, ny, nz = field.shape
        mc = wp.MarchingCubes(
            nx, ny, nz, max_verts=3 * field.size // 4, max_tris=2 * field.size // 2, device=field.device
        )
        mc.surface(field, threshold)
        return mc.verts, mc.indices

    return extract_old, "wp.MarchingCubes(nx, ny, nz, max_verts, max_tris, device).surface(field, threshold)"


def _bench_warp(vol: np.ndarray, dev: Any, repeat: int, slab: int, sync: Callable[[], None]) -> dict[str, Any]:
    import warp as wp

    extract, api = _warp_mc_extract()
    nz = vol.shape[0]
    # one launch dimension is nodes*3 int32 (counts / scan): keep a slab under 2^31 elements
    per_plane = 3 * vol.shape[1] * vol.shape[2]
    cap = max(1, (2**31 - 1) // per_plane - 1)
    cells = max(1, min(int(slab), cap))
    ranges = [(z0, min(z0 + cells, nz - 1)) for z0 in range(0, nz - 1, cells)]

    def run() -> tuple[int, int]:
        nv = nt = 0
        for z0, z1 in ranges:
            host = vol[z0 : z1 + 1].astype(np.float32)  # one float32 slab on the host at a time
            field = wp.array(host, dtype=wp.float32, device=dev)
            del host
            verts, idx = extract(field, float(BONE_LEVEL))
            v = verts.numpy()  # download (sync point)
            f = idx.numpy()
            nv += int(v.shape[0])
            nt += int(f.size // 3)
            del field, verts, idx, v, f
        return nv, nt

    mem = _DeviceMemory(dev)
    mem.start()
    res = _timed(run, repeat, sync)
    res.update(mem.result())
    res["input"] = "full volume"
    res["api"] = api
    res["slab_cells"] = cells
    res["slabs"] = len(ranges)
    res["notes"] = (
        "field passed as the (z, y, x) numpy layout, i.e. Warp's (nx, ny, nz) = (nz, ny, nx); only counts "
        "and time are compared. Per slab: host uint16->float32, upload, extract, download verts+indices. "
        "Vertices on slab seams are counted once per slab."
    )
    return res


# ----------------------------------------------------------------------------------------------------- main


def _parse_shape(text: str) -> tuple[int, int, int]:
    parts = [int(p) for p in text.replace("x", ",").split(",") if p.strip()]
    if len(parts) != 3 or min(parts) < 8:
        raise argparse.ArgumentTypeError(f"Expected Z,Y,X with every size >= 8, got {text!r}")
    return parts[0], parts[1], parts[2]


def _safe(name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    try:
        res = fn()
        res["available"] = True
        return res
    except Exception as exc:
        traceback.print_exc()
        return {"available": False, "error": f"{type(exc).__name__}: {exc}"}
    finally:
        _say(f"[mc33] {name} done (peak host RSS {_peak_rss_bytes() / 2**30:.2f} GiB)", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.mc33", description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:N] (default cpu)")
    ap.add_argument(
        "--shape", type=_parse_shape, default=None, help="Z,Y,X (default 256,256,256 on cpu, 952,1024,1024 on cuda)"
    )
    ap.add_argument("--repeat", type=int, default=3, help="timed runs after one warm-up (default 3)")
    ap.add_argument("--out", type=Path, required=True, help="result JSON path")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-skimage", action="store_true")
    ap.add_argument("--skip-warp", action="store_true")
    ap.add_argument(
        "--skimage-crop",
        choices=("auto", "full", "zslab", "cube"),
        default="auto",
        help="skimage input: full volume, central z-slab over the whole cross-section, or central cube, "
        "of at most --skimage-max-voxels (auto: full on cpu, zslab on cuda)",
    )
    ap.add_argument(
        "--skimage-max-voxels", type=int, default=256**3, help="voxel budget of the skimage crop (default 256^3)"
    )
    ap.add_argument("--warp-slab", type=int, default=256, help="z cells per slab for Warp's marching cubes")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")

    from engine.device import resolve_device

    dev = resolve_device(args.device)
    import warp as wp

    is_cuda = bool(dev.is_cuda)
    shape = args.shape or DEFAULT_SHAPE["cuda" if is_cuda else "cpu"]
    sk_mode = args.skimage_crop if args.skimage_crop != "auto" else ("zslab" if is_cuda else "full")

    def sync() -> None:
        if is_cuda:
            wp.synchronize_device(dev)

    _say(f"[mc33] device={dev} ({dev.name}) shape={shape} repeat={args.repeat}", flush=True)
    t0 = time.perf_counter()
    vol = bone_phantom(shape, seed=args.seed, dtype=np.uint16)
    gen_s = time.perf_counter() - t0
    nvox = int(vol.size)
    _say(f"[mc33] phantom {vol.shape} {vol.dtype} ({vol.nbytes / 2**30:.2f} GiB) in {gen_s:.1f} s", flush=True)

    results: dict[str, Any] = {}
    results["ours"] = _safe("ours", lambda: _bench_ours(vol, args.device, dev, args.repeat, sync))
    sk_crop = False
    if args.skip_skimage:
        results["skimage"] = {"available": False, "skipped": "--skip-skimage"}
    else:
        sub = _crop(vol, sk_mode, args.skimage_max_voxels)
        sk_crop = sub.shape != vol.shape
        results["skimage"] = _safe("skimage", lambda: _bench_skimage(sub, vol.shape, args.repeat, sk_mode))
        if sk_crop:  # same input for an apples-to-apples ratio
            label = f"crop '{sk_mode}' {tuple(sub.shape)}, the same input as skimage"
            results["ours_on_skimage_crop"] = _safe(
                "ours_on_skimage_crop", lambda: _bench_ours(sub, args.device, dev, args.repeat, sync, label)
            )
        del sub
    if args.skip_warp:
        results["warp_mc"] = {"available": False, "skipped": "--skip-warp"}
    else:
        results["warp_mc"] = _safe("warp_mc", lambda: _bench_warp(vol, dev, args.repeat, args.warp_slab, sync))

    results["ours_resident"] = _safe("ours_resident", lambda: _bench_ours_resident(vol, dev, args.repeat, sync))
    if not args.skip_warp:
        results["warp_mc_resident"] = _safe(
            "warp_mc_resident", lambda: _bench_warp_resident(vol, dev, args.repeat, args.warp_slab, sync)
        )

    for name, r in results.items():
        if r.get("available"):
            vox = int(r.get("voxels", nvox))
            r["voxels"] = vox
            r["voxels_per_s"] = vox / r["seconds"] if r["seconds"] > 0 else None
            r["device"] = "cpu (host, single-threaded)" if name == "skimage" else str(dev)

    def ratio(a: str, b: str) -> float | None:
        ra, rb = results[a], results[b]
        if ra.get("available") and rb.get("available") and ra.get("voxels_per_s") and rb.get("voxels_per_s"):
            return ra["voxels_per_s"] / rb["voxels_per_s"]
        return None

    ratios: dict[str, Any] = {
        "ours_over_skimage_voxels_per_s": ratio("ours", "skimage"),
        "ours_over_warp_mc_voxels_per_s": ratio("ours", "warp_mc"),
        "ours_resident_over_warp_mc_resident_voxels_per_s": (
            ratio("ours_resident", "warp_mc_resident") if "warp_mc_resident" in results else None
        ),
    }
    note = "speed ratios of voxels/s (>1: ours faster); skimage runs on the host CPU (single-threaded)"
    if sk_crop:
        ratios["ours_on_crop_over_skimage_voxels_per_s"] = ratio("ours_on_skimage_crop", "skimage")
        note += (
            f"; skimage got a '{sk_mode}' crop: ours_over_skimage compares ours on the full volume with skimage "
            "on the crop, ours_on_crop_over_skimage compares both on the same crop"
        )
    ratios["notes"] = note + "; warp_mc runs on the same device as ours, on the full volume."

    cuda_info: dict[str, Any] = {}
    if is_cuda:
        cuda_info = {
            "arch": getattr(dev, "arch", None),
            "total_memory_bytes": int(dev.total_memory),
            "mempool_enabled": bool(wp.is_mempool_enabled(dev)),
            "sm_count": getattr(dev, "sm_count", None),
        }
    report = {
        "benchmark": "mc33_isosurface",
        "date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "device": {
            "requested": args.device,
            "warp_device": str(dev),
            "warp_device_name": dev.name,
            "is_cuda": is_cuda,
            **cuda_info,
            "cpu_model": _cpu_model(),
            "cpu_cores": os.cpu_count(),
            "cpu_cores_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "host_memory_bytes": _host_memory_bytes(),
            "platform": platform.platform(),
        },
        "volume": {
            "generator": "benchmarks.phantom.bone_phantom",
            "seed": args.seed,
            "units": "HU + 1024",
            "generation_seconds": gen_s,
            "nbytes": int(vol.nbytes),
        },
        "shape": list(shape),
        "voxels": nvox,
        "level": BONE_LEVEL,
        "dtype": str(vol.dtype),
        "repeats": args.repeat,
        "timing_method": (
            f"median of {args.repeat} after 1 warm-up; wall clock (time.perf_counter), end to end from "
            "a host numpy array to host numpy results, device synchronised before/after each run"
        ),
        "results": results,
        "ratios": ratios,
        "peak_host_rss_bytes": _peak_rss_bytes(),
        "git_commit": _git_commit(),
        "versions": _versions(),
        "command": "python -m benchmarks.mc33 " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")

    _say(f"\nMC33 benchmark  {dev} ({dev.name})  shape={shape}  level={BONE_LEVEL}  median of {args.repeat}")
    for name, r in results.items():
        if r.get("available"):
            _say(
                f"  {name:20s} {r['seconds']:8.3f} s  {r['voxels_per_s'] / 1e6:9.1f} Mvox/s  "
                f"verts={r['vertices']:>11,d}  tris={r['triangles']:>11,d}  [{r['input']}]"
            )
        else:
            _say(f"  {name:20s} unavailable: {r.get('skipped') or r.get('error')}")
    for k, v in ratios.items():
        if k == "notes":
            continue
        _say(f"  {k}: {'n/a' if v is None else f'{v:.2f}x'}")
    o = results["ours"]
    if o.get("available"):
        pk = o.get("peak_device_memory_bytes")
        _say(
            f"  ours peak device memory: {'n/a' if pk is None else f'{pk / 2**30:.2f} GiB'}; engine estimate "
            f"{o['peak_device_memory_engine_estimate_bytes'] / 2**30:.2f} GiB; slabs={o['stats']['slabs']}"
        )
    _say(f"  wrote {args.out}")
    return 0 if results["ours"].get("available") else 1


if __name__ == "__main__":
    sys.exit(main())
