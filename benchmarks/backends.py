"""The whole ``reconstruct`` on each backend (issue 28): Warp (CPU or CUDA) against OpenCL (PoCL on the CPU, or a
GPU's OpenCL driver), on every real scan in ../shared/data and a bone phantom, with the final model's topology; and
(``--labels N@Z,Y,X``) a synthetic N-label map through ``label_models`` (issue 40: label maps on every backend).

    python -m benchmarks.backends --devices cpu,opencl [--data ../shared/data] [--phantom Z,Y,X] [--repeat N]
                                  [--scans cranium_ct,...] --out benchmarks/results/backends_cpu.json
    python -m benchmarks.backends --devices cuda:0,opencl:0 --phantom 952,1024,1024 --no-scans --out ...
    python -m benchmarks.backends --devices cuda:0,opencl:0 --phantom '' --no-scans --labels 100@400,512,512 --out ...

Per input and device: one warm-up run (kernel builds), then the median of ``repeat`` runs of ``reconstruct`` (the
paper's pipeline: Gaussian, MC33, decimation to 0.2, one smoothing iteration, no cleaning; the scan's bone level
from its meta.json) with the stage times of the median run, and the final model's topology (faces, components,
Euler characteristic, watertight, 2-manifold) and a hash of its mesh. Ratios are the first device's seconds over
each other's (above 1: the other is faster), from the same run; ``identical_topology`` compares the models'
topology with the first device's, ``identical_mesh`` their vertices and faces bit for bit.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

from benchmarks.report import write_json
from engine.params import IsoParams, ReconParams
from engine.types import Volume

TOPOLOGY = ("n_faces", "n_vertices", "components", "euler", "watertight", "manifold")


def _scans(data_dir: Path, names: list[str] | None) -> dict[str, Volume]:
    """Every ../shared/data folder with a PNG stack and a meta.json (spacing, bone level), as volumes."""
    from engine.io.stack import load_slice_zip

    out: dict[str, Volume] = {}
    for meta_path in sorted(data_dir.glob("*/meta.json")):
        name = meta_path.parent.name
        meta = json.loads(meta_path.read_text())
        stack = (meta.get("files") or {}).get("slices_png16")
        if stack is None or (names and name not in names) or not (meta_path.parent / stack).exists():
            continue
        if None in meta["spacing_mm_xyz"]:  # a gantry-tilt series: its PNG stack has no single slice step
            continue
        spacing = tuple(float(v) for v in meta["spacing_mm_xyz"][::-1])
        source = {"file": stack, "level": float(meta["iso_bone_stored"])}
        out[name] = Volume(load_slice_zip(meta_path.parent / stack), spacing, source=source)  # type: ignore[arg-type]
    return out


def _phantom(shape: tuple[int, int, int]) -> Volume:
    from benchmarks.phantom import bone_phantom
    from engine.data.phantom import BONE_LEVEL

    return Volume(bone_phantom(shape), (0.05, 0.05, 0.05), source={"generator": "phantom", "level": BONE_LEVEL})


def _params(volume: Volume) -> ReconParams:
    return ReconParams(iso=IsoParams(iso=float(volume.source["level"])), body=None, islands=None)


def _run(volume: Volume, device: str, repeat: int) -> dict[str, Any]:
    from engine.job.pipeline import reconstruct

    params = _params(volume)
    t0 = time.perf_counter()
    reconstruct(volume, params, device=device)  # warm-up: kernel builds, contexts
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        recon = reconstruct(volume, params, device=device)
        mesh = recon.mesh  # the finished model on the host: part of the work
        runs.append((time.perf_counter() - t0, recon, mesh))
    runs.sort(key=lambda r: r[0])
    seconds, recon, mesh = runs[len(runs) // 2]
    stats = recon.report["mesh"]
    return {
        "device": recon.report["device"],
        "first_run_seconds": first,
        "seconds": seconds,
        "all_seconds": sorted(r[0] for r in runs),
        "stage_seconds": recon.report["stage_seconds"],
        "topology": {k: stats.get(k) for k in TOPOLOGY},
        "mesh_sha256": hashlib.sha256(mesh.vertices.tobytes() + mesh.faces.tobytes()).hexdigest(),
    }


def _label_map(spec: str) -> Any:
    """``N@Z,Y,X``: the labels benchmark's synthetic N-label map (touching cells in a body, 1 x 0.8 x 0.8 mm)."""
    from benchmarks.labels_speed import synthetic_map
    from engine.io.labelmaps import make_label_volume

    n, _, size = spec.partition("@")
    shape = tuple(int(v) for v in size.split(","))
    data = synthetic_map((shape[0], shape[1], shape[2]), int(n))
    eye = ((1, 0, 0), (0, 1, 0), (0, 0, 1))
    return make_label_volume(data, (1.0, 0.8, 0.8), (0.0, 0.0, 0.0), eye, (), {"format": "synthetic"})


def _run_labels(lv: Any, device: str, repeat: int) -> dict[str, Any]:
    """``label_models`` (every label meshed in one batch, decimated to 0.2 by area, smoothed, split into parts)."""
    from engine.labels import label_models

    t0 = time.perf_counter()
    label_models(lv, device=device)  # warm-up: kernel builds, contexts
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        models = label_models(lv, device=device)
        runs.append((time.perf_counter() - t0, models))
    runs.sort(key=lambda r: r[0])
    seconds, models = runs[len(runs) // 2]
    digest = hashlib.sha256()
    for part in models.parts:
        digest.update(part.vertices_xyz.tobytes() + part.faces.tobytes())
    info = models.report["labels_mesh"]
    return {
        "device": info.get("backend", device),
        "first_run_seconds": first,
        "seconds": seconds,
        "all_seconds": sorted(r[0] for r in runs),
        "stage_seconds": info["seconds"],
        "topology": {
            "parts": len(models.parts),
            "n_faces": int(sum(p.stats["faces"] for p in models.parts)),
            "watertight_parts": int(sum(bool(p.stats["watertight"]) for p in models.parts)),
        },
        "mesh_sha256": digest.hexdigest(),
    }


def _compare(entry: dict[str, Any], devices: list[str]) -> None:
    base = entry[devices[0]]
    for dev in devices[1:]:
        other = entry[dev]
        entry.setdefault("ratio_first_over", {})[dev] = base["seconds"] / other["seconds"]
        entry.setdefault("identical_topology", {})[dev] = other["topology"] == base["topology"]
        entry.setdefault("identical_mesh", {})[dev] = other["mesh_sha256"] == base["mesh_sha256"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--devices", default="cpu,opencl", help="comma-separated: the first is the reference")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--scans", default="", help="only these ../shared/data folders (default: every one)")
    parser.add_argument("--no-scans", action="store_true", help="only the phantom")
    parser.add_argument("--phantom", default="256,256,256", help="Z,Y,X of the bone phantom ('' for none)")
    parser.add_argument("--labels", default="", help="N@Z,Y,X: also a synthetic N-label map ('' for none)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--machine", default=platform.node())
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    devices = [d.strip() for d in args.devices.split(",") if d.strip()]
    inputs = {} if args.no_scans else _scans(args.data, [s for s in args.scans.split(",") if s])
    if args.phantom:
        shape = tuple(int(v) for v in args.phantom.split(","))
        inputs[f"phantom_{'x'.join(map(str, shape))}"] = _phantom(shape)  # type: ignore[arg-type]
    if args.labels:
        inputs[f"labels_{args.labels.replace('@', '_').replace(',', 'x')}"] = _label_map(args.labels)
    report: dict[str, Any] = {
        "benchmark": "backends",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": args.machine,
        "host": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "devices": devices,
        "repeat": args.repeat,
        "pipeline": "paper: Gaussian, MC33, decimation 0.2, 1 smoothing iteration, no body mask or speck removal",
        "inputs": {},
    }
    for name, volume in inputs.items():
        labels = not isinstance(volume, Volume)
        shape = list(volume.labels.shape if labels else volume.data.shape)
        entry: dict[str, Any] = {"shape_zyx": shape}
        entry["level" if not labels else "labels"] = volume.source["level"] if not labels else len(volume.segments)
        for dev in devices:
            print(f"[backends] {name} {shape} on {dev}", flush=True)
            entry[dev] = (_run_labels if labels else _run)(volume, dev, args.repeat)
            print(f"  {entry[dev]['seconds']:.3f} s, {entry[dev]['topology']}", flush=True)
        _compare(entry, devices)
        report["inputs"][name] = entry
        write_json(args.out, report)
    ratios = [e["ratio_first_over"][d] for e in report["inputs"].values() for d in devices[1:]]
    report["min_ratio"] = min(ratios) if ratios else None
    write_json(args.out, report)
    print(f"[backends] wrote {args.out}; ratios {[round(r, 2) for r in ratios]}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
