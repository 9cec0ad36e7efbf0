"""The volume stages on OpenCL against Warp: the 3x3x3 Gaussian and MC33 on Warp's CPU path and on an OpenCL device
(PoCL on this machine's CPU cores), for the headsq scan (engine/data) and a bone phantom (256^3 by default).

    python -m benchmarks.opencl_stages [--opencl opencl:N] [--warp cpu|cuda:N] [--phantom Z,Y,X] [--repeat N]
                                       [--no-headsq] --out benchmarks/results/opencl_stages_cpu.json

Per input and backend: the volume is uploaded, smoothed (``engine.volume.gaussian.smooth_volume``) and extracted
(``engine.isosurface.extract_isosurface``, closed, at the bone level) on the device, each stage synchronised and
timed (a first run builds the kernels and is reported apart as ``first_run_seconds``; then the median of
``repeat`` runs). The two meshes are compared (the same faces and vertices bit for bit: ``identical``) and the
ratios Warp / OpenCL (above 1: OpenCL faster) come from the same run.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

STAGES = ("upload", "gaussian", "mc33", "download")


def _inputs(args: argparse.Namespace) -> dict[str, tuple[np.ndarray, tuple[float, float, float], float]]:
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
    from engine.data.phantom import BONE_LEVEL, bone_phantom
    from engine.io.stack import load_slice_zip

    out = {}
    if not args.no_headsq:
        out["headsq"] = (load_slice_zip(HEADSQ_ZIP), HEADSQ_SPACING_ZYX_MM, 1150.0)
    shape = tuple(int(s) for s in args.phantom.split(","))
    out["phantom_" + "x".join(map(str, shape))] = (bone_phantom(shape), (1.0, 1.0, 1.0), BONE_LEVEL)  # type: ignore[arg-type]
    return out


def _run_once(be: Any, vol: np.ndarray, spacing: Any, level: float) -> tuple[dict[str, float], Any]:
    from engine.isosurface import extract_isosurface
    from engine.params import GaussianParams
    from engine.volume.gaussian import smooth_volume

    times: dict[str, float] = {}
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        be.synchronize()
        now = time.perf_counter()
        times[name] = now - t
        t = now

    field = be.from_host(vol)
    lap("upload")
    field = smooth_volume(field, GaussianParams())
    lap("gaussian")
    v, f = extract_isosurface(field, level, spacing=spacing, closed=True)
    lap("mc33")
    mesh = (be.to_host(v).reshape(-1, 3), be.to_host(f).reshape(-1, 3))
    lap("download")
    times["total"] = sum(times[s] for s in STAGES)
    return times, mesh


def _measure(be: Any, vol: np.ndarray, spacing: Any, level: float, repeat: int) -> tuple[dict[str, Any], Any]:
    first, mesh = _run_once(be, vol, spacing, level)
    runs = [_run_once(be, vol, spacing, level)[0] for _ in range(repeat)]
    med = {k: statistics.median(r[k] for r in runs) for k in (*STAGES, "total")}
    out = {
        "device": be.label,
        "first_run_seconds": first["total"],
        "seconds": med,
        "faces": len(mesh[1]),
        "vertices": len(mesh[0]),
        "voxels_per_s": vol.size / med["total"],
        "mesh_sha256": hashlib.sha256(mesh[0].tobytes() + mesh[1].tobytes()).hexdigest(),
    }
    return out, mesh


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for name in ("bonemesh", "warp-lang", "pyopencl", "numpy"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = "not installed"
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--opencl", default="opencl", help="the OpenCL device: opencl or opencl:N")
    ap.add_argument("--warp", default="cpu", help="the Warp device to compare with (cpu, cuda:N)")
    ap.add_argument("--phantom", default="256,256,256", help="bone phantom shape Z,Y,X")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-headsq", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/opencl_stages_cpu.json"))
    args = ap.parse_args(argv)

    from engine.backend import get_backend
    from engine.device import init_runtime

    init_runtime()
    backends = {"warp": get_backend(args.warp), "opencl": get_backend(args.opencl)}
    report: dict[str, Any] = {
        "benchmark": "opencl_stages",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "host": {"cpus": os.cpu_count(), "machine": platform.machine(), "processor": platform.processor()},
        "devices": {k: be.label for k, be in backends.items()},
        "repeat": args.repeat,
        "versions": _versions(),
        "inputs": {},
    }
    for name, (vol, spacing, level) in _inputs(args).items():
        entry: dict[str, Any] = {"shape_zyx": list(vol.shape), "dtype": str(vol.dtype), "level": level}
        meshes = {}
        for key, be in backends.items():
            entry[key], meshes[key] = _measure(be, vol, spacing, level, args.repeat)
            print(f"{name} {key}: {entry[key]['seconds']['total']:.3f} s, {entry[key]['faces']:,} faces", flush=True)
        a, b = meshes["warp"], meshes["opencl"]
        entry["identical"] = bool(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]))
        w, c = entry["warp"]["seconds"], entry["opencl"]["seconds"]
        entry["ratios_warp_over_opencl"] = {k: w[k] / c[k] if c[k] > 0 else None for k in ("gaussian", "mc33", "total")}
        report["inputs"][name] = entry
        print(f"{name}: identical={entry['identical']} ratios={entry['ratios_warp_over_opencl']}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0 if all(e["identical"] for e in report["inputs"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
