"""Defect template speed (issue 31): plane + template of the cranium (its real defect), warm, on one device.

    python -m benchmarks.defect_speed --device cpu|cuda:0 [--data PATH] [--repeat 5] --out result.json

PATH is the cranium's PNG zip (../shared/data/cranium_ct/cranium_ct_png16.zip, the default) or a ``.npz`` with its
``data`` (108 x 256 x 256, HU + 1024), for a machine without the image codecs. The first run compiles Warp's kernels
and is not timed; then ``--repeat`` runs of ``engine.defect.run`` (the symmetry plane, then the template, its implant
surface included), each synchronised, with their stages (``DefectResult.seconds``): the median is reported.
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", default=str(CRANIUM))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results/defect_speed_cpu.json")
    args = ap.parse_args(argv)
    import warp as wp

    from engine.defect import DefectParams, run
    from engine.device import init_runtime, resolve_device
    from engine.params import OrientParams

    init_runtime()
    dev = resolve_device(args.device)
    volume = _volume(Path(args.data))
    orient = OrientParams(first_slice="inferior", flip_ap=True)
    t0 = time.perf_counter()
    first = run(volume, DefectParams(), LEVEL, dev, orient=orient)
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(args.repeat):
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        res = run(volume, DefectParams(), LEVEL, dev, orient=orient)
        wp.synchronize_device(dev)
        runs.append({"total": time.perf_counter() - t0, **res.seconds})
    keys = list(runs[0])
    median = {k: float(np.median([r.get(k, 0.0) for r in runs])) for k in keys}
    info = res.to_json()
    result = {
        "benchmark": "defect_speed",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "device": str(dev),
        "device_name": getattr(dev, "name", str(dev)),
        "machine": platform.processor() or platform.machine(),
        "scan": "cranium_ct 108x256x256, spacing z,y,x 1.5,0.957,0.957 mm, level 1324 (300 HU + 1024)",
        "first_run_with_compile_s": round(compile_s, 3),
        "repeat": args.repeat,
        "median_seconds": {k: round(v, 4) for k, v in median.items()},
        "runs": [{k: round(v, 4) for k, v in r.items()} for r in runs],
        "defect": {k: info["defect"][k] for k in ("side", "volume_mm3", "area_mm2", "slices", "rim")},
        "plane": info["plane"],
        "same_as_first_run": bool(abs(first.volume_mm3 - res.volume_mm3) < 1e-6 * max(1.0, res.volume_mm3)),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("device_name", "first_run_with_compile_s", "median_seconds", "defect")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
