"""Defect template speed (issue 31): plane + template of the cranium (its real defect), warm, on each device.

    python -m benchmarks.defect_speed --device cpu|cuda:0|opencl[:N] [--data PATH] [--repeat 5] --out result.json
    python -m benchmarks.defect_speed --device cuda:0,opencl:0 --out result.json   # NVIDIA: CUDA against OpenCL
    python -m benchmarks.defect_speed --device cpu --before /tmp/before   # against a checkout of the code before

PATH is the cranium's PNG zip (../shared/data/cranium_ct/cranium_ct_png16.zip, the default) or a ``.npz`` with its
``data`` (108 x 256 x 256, HU + 1024), for a machine without the image codecs. The first run compiles Warp's kernels
and is not timed; then ``--repeat`` runs of ``engine.defect.run`` (the symmetry plane, then the template, its implant
surface included), each synchronised, with their stages (``DefectResult.seconds``): the median is reported. With
several devices (issue 40: the defect on every backend), each is measured in turn; ``identical_to_first`` says
whether its defect (mask, measures) is the first device's, ``ratio_first_over_this`` the first device's median over
its own (above 1: it is faster). The top-level timing fields are the first device's. ``plane_on_device``: the
masks and the symmetry plane with their work on the device (issue 42: ``engine.defect.ops.bone_and_skull`` and
``find_symmetry_plane(..., device=...)``; ``run`` finds both on the host until it passes its device on), median
seconds of each and the plane's distance from ``run``'s.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

CRANIUM = Path(__file__).resolve().parents[2] / "shared" / "data" / "cranium_ct" / "cranium_ct_png16.zip"
SPACING = (1.5, 0.9570312, 0.9570312)
LEVEL = 1324.0  # 300 HU + 1024


def _volume(path: Path) -> Any:
    from engine.types import Volume

    if path.suffix == ".npz":
        return Volume(np.load(path)["data"], SPACING)
    from engine.io import load_volume

    return load_volume(path, spacing_zyx_mm=SPACING)


def _measure(volume: Any, device: str, repeat: int) -> dict[str, Any]:
    """One device: a first run (kernel compiles and program builds), then ``repeat`` synchronised runs."""
    from engine.defect import DefectParams, run
    from engine.device import resolve_backend
    from engine.params import OrientParams

    be = resolve_backend(device)
    orient = OrientParams(first_slice="inferior", flip_ap=True)
    t0 = time.perf_counter()
    first = run(volume, DefectParams(), LEVEL, be, orient=orient)
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        be.synchronize()
        t0 = time.perf_counter()
        res = run(volume, DefectParams(), LEVEL, be, orient=orient)
        be.synchronize()
        runs.append({"total": time.perf_counter() - t0, **res.seconds})
    median = {k: float(np.median([r.get(k, 0.0) for r in runs])) for k in runs[0]}
    on_device = _plane_on_device(volume, be, orient, repeat, res.plane)
    return {
        "device": be.spec,
        "device_name": be.label,
        "backend": be.kind,
        "first_run_with_compile_s": round(compile_s, 3),
        "median_seconds": {k: round(v, 4) for k, v in median.items()},
        "runs": [{k: round(v, 4) for k, v in r.items()} for r in runs],
        "same_as_first_run": bool(abs(first.volume_mm3 - res.volume_mm3) < 1e-6 * max(1.0, res.volume_mm3)),
        "plane_on_device": on_device,
        "_result": res,
    }


def _plane_on_device(volume: Any, be: Any, orient: Any, repeat: int, plane: Any) -> dict[str, Any]:
    """The masks and the symmetry plane with their work on the device (issue 42: ``ops.bone_and_skull(be, ...)``,
    ``find_symmetry_plane(..., device=be, where="device")`` given that skull, on a CPU device too): a first run
    (builds), then ``repeat`` synchronised runs; the median seconds of each, whether the masks are the host's, and
    how far the plane is from ``plane`` (``run``'s)."""
    from engine.defect import DefectParams, find_symmetry_plane
    from engine.defect.grid import bone_and_skull
    from engine.defect.ops import bone_and_skull as bone_and_skull_on

    host = bone_and_skull(volume.data, LEVEL)
    bone, skull = bone_and_skull_on(be, volume.data, LEVEL)
    find_symmetry_plane(volume, LEVEL, DefectParams(), orient=orient, skull=skull, device=be, where="device")
    masks, planes = [], []
    for _ in range(repeat):
        be.synchronize()
        t0 = time.perf_counter()
        bone, skull = bone_and_skull_on(be, volume.data, LEVEL)
        t1 = time.perf_counter()
        dev = find_symmetry_plane(volume, LEVEL, DefectParams(), orient=orient, skull=skull, device=be, where="device")
        be.synchronize()
        masks.append(t1 - t0)
        planes.append(time.perf_counter() - t1)
    cos = min(1.0, abs(float(np.dot(dev.normal_grid, plane.normal_grid))))
    return {
        "masks_median_seconds": round(float(np.median(masks)), 4),
        "plane_median_seconds": round(float(np.median(planes)), 4),
        "masks_plus_plane_median_seconds": round(float(np.median(np.add(masks, planes))), 4),
        "masks_runs": [round(v, 4) for v in masks],
        "plane_runs": [round(v, 4) for v in planes],
        "masks_same_as_host": bool(np.array_equal(bone, host[0]) and np.array_equal(skull, host[1])),
        "iterations": dev.iterations,
        "angle_to_run_plane_deg": round(float(np.degrees(np.arccos(cos))), 5),
        "offset_to_run_plane_mm": round(dev.offset_grid_mm - plane.offset_grid_mm, 5),
    }


def _load_average() -> list[float] | None:
    import os

    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on this platform
        return None


def _before(tree: Path, args: Any) -> dict[str, Any]:
    """The same measure with the code in ``tree`` (its own ``benchmarks.defect_speed``, a subprocess)."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "before.json"
        cmd = [sys.executable, "-m", "benchmarks.defect_speed", "--device", args.device.split(",")[0],
               "--data", str(Path(args.data).resolve()), "--repeat", str(args.repeat), "--out", str(out)]  # fmt: skip
        subprocess.run(cmd, cwd=tree, check=True, stdout=subprocess.DEVNULL)
        result: dict[str, Any] = json.loads(out.read_text())
    rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tree, capture_output=True, text=True)
    result["commit"] = rev.stdout.strip() or None
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="a device, or several separated by commas (cuda:0,opencl:0)")
    ap.add_argument("--data", default=str(CRANIUM))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results/defect_speed_cpu.json")
    ap.add_argument("--before", default=None, metavar="TREE",
                    help="a checkout of the code before (git worktree add TREE REV): measured in the same run, first, "
                         "and the ratio before/after reported per stage")  # fmt: skip
    args = ap.parse_args(argv)
    load_at_start = _load_average()
    before = _before(Path(args.before), args) if args.before else None
    from engine.device import init_runtime

    init_runtime()
    volume = _volume(Path(args.data))
    rows = [_measure(volume, d.strip(), args.repeat) for d in args.device.split(",") if d.strip()]
    ref = rows[0]["_result"]
    for row in rows:
        res = row.pop("_result")
        row["identical_to_first"] = bool(
            np.array_equal(res.mask, ref.mask) and res.to_json()["defect"] == ref.to_json()["defect"]
        )
        row["ratio_first_over_this"] = round(rows[0]["median_seconds"]["total"] / row["median_seconds"]["total"], 3)
    info = ref.to_json()
    result = {
        "benchmark": "defect_speed",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        **{k: rows[0][k] for k in ("device", "device_name", "first_run_with_compile_s", "median_seconds", "runs")},
        "machine": platform.processor() or platform.machine(),
        "scan": "cranium_ct 108x256x256, spacing z,y,x 1.5,0.957,0.957 mm, level 1324 (300 HU + 1024)",
        "repeat": args.repeat,
        "devices": rows,
        "defect": {k: info["defect"][k] for k in ("side", "volume_mm3", "area_mm2", "slices", "rim")},
        "plane": info["plane"],
        "same_as_first_run": rows[0]["same_as_first_run"],
        # the host's load average (1, 5, 15 min) at the start and the end: other work on the machine slows every
        # stage, the host's most
        "load_average": {"start": load_at_start, "end": _load_average()},
    }
    if before is not None:
        now = rows[0]["median_seconds"]
        result["before"] = {
            "tree": args.before,
            "commit": before.get("commit"),
            "median_seconds": before["median_seconds"],
            "ratio_before_over_after": {k: round(v / now[k], 3) for k, v in before["median_seconds"].items()
                                        if k in now and now[k] > 0},
            "defect": before.get("defect"),
        }  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    keys = ("device_name", "first_run_with_compile_s", "median_seconds", "identical_to_first", "plane_on_device")
    summary = [{k: r[k] for k in keys} for r in rows]
    print(json.dumps({"devices": summary, "defect": result["defect"], "before": result.get("before")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
