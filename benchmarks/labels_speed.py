"""A model per label, batched (``engine.labels.label_models``): seconds for an N-label map of a given size.

The map is synthetic and TotalSegmentator-like: an ellipsoidal body split into N Voronoi cells (seeded, coarse
cells upsampled, so neighbouring labels touch on most of their faces), every cell one label. The target of issue 30
is a 100-label 512x512x400 map in <= 2 s on an H100. Each run times ``label_models`` whole (boxes, atlases, MC33,
decimation with the budget shared by area, smoothing, the split into parts in the patient frame, the per-label
stats); the first (warm-up) run compiles the kernels and is reported apart.

    python -m benchmarks.labels_speed --size 400,512,512 --labels 100 --device cuda:0 \
        --out benchmarks/results/labels_speed_cuda.json
    python -m benchmarks.labels_speed --size 16,32,32 --labels 4 --device cpu --repeat 1 --out /tmp/l.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np


def synthetic_map(shape: tuple[int, int, int], labels: int, seed: int = 0) -> np.ndarray:
    """An ellipsoidal body of ``labels`` touching Voronoi cells (values 1..labels; uint8 up to 255 labels)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    coarse = tuple(max(2, -(-n // 8)) for n in shape)
    grid = np.stack(np.meshgrid(*[np.arange(n) + 0.5 for n in coarse], indexing="ij"), axis=-1).reshape(-1, 3)
    pts = rng.uniform(-1, 1, (labels * 4, 3))
    pts = pts[(pts**2).sum(axis=1) <= 0.8**2][:labels]  # seeds inside the body, so every cell holds voxels
    seeds = (pts * np.array([0.48, 0.45, 0.45]) + 0.5) * np.asarray(coarse)
    cells = cKDTree(seeds).query(grid)[1].reshape(coarse).astype(np.uint8 if labels < 256 else np.uint16) + 1
    for axis, (n, c) in enumerate(zip(shape, coarse, strict=True)):
        cells = np.repeat(cells, -(-n // c), axis=axis)
    full = cells[: shape[0], : shape[1], : shape[2]]
    z, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    inside = ((z - shape[0] / 2) / (0.48 * shape[0])) ** 2 + ((y - shape[1] / 2) / (0.45 * shape[1])) ** 2
    inside = inside + ((x - shape[2] / 2) / (0.45 * shape[2])) ** 2 <= 1
    out: np.ndarray = np.where(inside, full, 0).astype(cells.dtype)
    return out


def _run(lv: Any, device: str) -> dict[str, Any]:
    from engine.labels import label_models

    t0 = time.perf_counter()
    models = label_models(lv, device=device)
    seconds = time.perf_counter() - t0
    stats = [p.stats for p in models.parts]
    info = models.report["labels_mesh"]
    return {
        "seconds": seconds,
        "stage_seconds": info["seconds"],
        "mc33_faces": info["mc33_faces"],
        "faces": int(sum(s["faces"] for s in stats)),
        "parts": len(stats),
        "watertight_parts": int(sum(bool(s["watertight"]) for s in stats)),
        "atlases": info["atlases"],
        "decimate": {k: v for k, v in info["decimate"].items() if k != "share_faces"},
    }


def main(argv: list[str] | None = None) -> int:
    from engine.io.labelmaps import make_label_volume

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="400,512,512", help="Z,Y,X of the map")
    ap.add_argument("--labels", type=int, default=100)
    ap.add_argument("--spacing", default="1.0,0.8,0.8", help="Z,Y,X voxel size in mm")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    shape = tuple(int(v) for v in args.size.split(","))
    spacing = tuple(float(v) for v in args.spacing.split(","))
    t0 = time.perf_counter()
    labels = synthetic_map((shape[0], shape[1], shape[2]), args.labels)
    made = time.perf_counter() - t0
    lv = make_label_volume(
        labels,
        (spacing[0], spacing[1], spacing[2]),
        (0.0, 0.0, 0.0),
        ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
        (),
        {"format": "synthetic"},
    )
    report: dict[str, Any] = {
        "benchmark": "labels_speed",
        "device": args.device,
        "size_zyx": list(shape),
        "labels_asked": args.labels,
        "labels_present": len(lv.segments),
        "spacing_zyx_mm": list(spacing),
        "map_seconds": made,
        "target": "100 labels, 512x512x400, <= 2 s on an H100 (issue 30)",
        "platform": platform.platform(),
    }
    try:
        report["warmup"] = _run(lv, args.device)
        report["runs"] = [_run(lv, args.device) for _ in range(args.repeat)]
        times = [r["seconds"] for r in report["runs"]]
        report["seconds_min"], report["seconds_median"] = min(times), float(np.median(times))
    except Exception as exc:  # recorded, so a failing size still leaves its JSON
        report["error"] = f"{type(exc).__name__}: {exc}"
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=2))
    print(json.dumps({k: report.get(k) for k in ("size_zyx", "labels_present", "seconds_min", "error")}))
    return 1 if "error" in report else 0


if __name__ == "__main__":
    raise SystemExit(main())
