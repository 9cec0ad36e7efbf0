"""Pipeline benchmark: per-stage wall times of ``engine.reconstruct`` (defaults: the paper's best combination).

    python -m benchmarks.pipeline --device cpu|cuda:0 [--data ../shared/data] [--phantom Z,Y,X] [--repeat N]
                                  --out result.json

Inputs: the cranium and pelvis CT scans (PNG stacks of HU + 1024, loaded with their spacing, level = bone
preset 300 HU via ``hu_offset=1024``) when the data folder is present, and the bone phantom of
``benchmarks.phantom`` (uint16 HU + 1024). Each input: one warm-up run (kernel compilation), then the median of
N runs of the whole ``reconstruct`` plus the stage times of the median run; ``write_outputs`` of that run's mesh is
timed N times too (median, with its parts).
The warm-up runs on the central 48 slices (compiling the kernels), not the whole volume.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.phantom import bone_phantom
from benchmarks.report import write_json
from engine.params import IsoParams, ReconParams
from engine.types import Volume

SCANS = {
    "cranium_ct": ("cranium_ct_png16.zip", (1.5, 0.9570312, 0.9570312)),
    "pelvis_ct": ("pelvis_ct_png16.zip", (5.0, 1.663, 1.663)),
}


def _inputs(data_dir: Path, phantom_shape: tuple[int, int, int] | None) -> dict[str, Volume]:
    from engine.io.stack import load_slice_zip

    out: dict[str, Volume] = {}
    for name, (zipname, spacing) in SCANS.items():
        path = data_dir / name / zipname
        if path.exists():
            out[name] = Volume(load_slice_zip(path), spacing, source={"file": str(path)})
    if phantom_shape:
        out[f"phantom_{'x'.join(map(str, phantom_shape))}"] = Volume(
            bone_phantom(phantom_shape), (0.05, 0.05, 0.05), source={"generator": "benchmarks.phantom"}
        )
    return out


# "paper": the paper's pipeline (Gaussian, MC33, decimation 0.2, one smoothing iteration), no cleaning;
# "product": the product's defaults (also the body mask and speck removal)
CONFIGS = {
    "paper": ReconParams(iso=IsoParams(preset="bone", hu_offset=1024.0), body=None, islands=None),
    "product": ReconParams(iso=IsoParams(preset="bone", hu_offset=1024.0)),
}


def _bench(volume: Volume, device: str, repeat: int, params: ReconParams) -> dict[str, Any]:
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    # warm-up (kernel compilation) on the first slices only: a full extra run of a 1 G voxel job costs minutes
    nz = volume.data.shape[0]
    warm = dataclasses.replace(volume, data=volume.data[nz // 2 - min(24, nz // 2) : nz // 2 + min(24, nz // 2)])
    with tempfile.TemporaryDirectory() as tmp:  # the output kernels compile here too
        write_outputs(reconstruct(warm, params, device=device), tmp, params, device=device)
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()

        def progress(stage: str, fraction: float, t0: float = t0) -> None:
            if fraction in (0.0, 1.0) or stage != "decimate":
                print(f"    {time.perf_counter() - t0:8.2f} s  {stage} {fraction:.2f}", flush=True)

        recon = reconstruct(volume, params, device=device, on_progress=progress)
        runs.append((time.perf_counter() - t0, recon))
    runs.sort(key=lambda r: r[0])
    seconds, recon = runs[len(runs) // 2]
    writes = []
    for _ in range(repeat):  # the median run's mesh, written N times into fresh folders
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_outputs(recon, tmp, params, device=device)
            writes.append((time.perf_counter() - t0, recon.report.get("write_seconds")))
    writes.sort(key=lambda w: w[0])
    write_s, write_parts = writes[len(writes) // 2]
    rep = recon.report
    return {
        "shape_zyx": list(volume.data.shape),
        "voxels": int(volume.data.size),
        "reconstruct_seconds": seconds,
        "reconstruct_seconds_all": [r[0] for r in runs],
        "stage_seconds": rep["stage_seconds"],
        "finish_seconds": rep.get("finish_seconds"),
        "write_outputs_seconds": write_s,
        "write_outputs_seconds_all": [w[0] for w in writes],
        "write_outputs_parts": write_parts,
        "counts": rep["counts"],
        "exports": rep.get("exports"),
        "decimate": rep.get("decimate"),
        "mesh": rep["mesh"],
        "islands": rep.get("islands"),
        "body_mask": rep.get("body_mask"),
        "iso_level": rep["iso_level"],
        "device": rep["device"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--phantom", default=None, help="phantom shape Z,Y,X (default: none)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--config", default="paper", choices=sorted(CONFIGS), help="parameters (see CONFIGS)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    shape = tuple(int(s) for s in args.phantom.split(",")) if args.phantom else None
    results = {}
    for name, vol in _inputs(args.data, shape).items():  # type: ignore[arg-type]
        print(f"[pipeline] {name} {vol.data.shape}", flush=True)
        results[name] = _bench(vol, args.device, args.repeat, CONFIGS[args.config])
        r = results[name]
        stages = ", ".join(f"{k} {v:.3f}" for k, v in r["stage_seconds"].items())
        print(
            f"  reconstruct {r['reconstruct_seconds']:.3f} s ({stages}); outputs {r['write_outputs_seconds']:.3f} s;"
            f" faces {r['counts']['isosurface']['faces']:,} -> {r['mesh']['n_faces']:,}",
            flush=True,
        )
    report = {
        "benchmark": "pipeline",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "device": args.device,
        "timing": f"median of {args.repeat} after 1 warm-up; stage times of the median run",
        "config": args.config,
        "parameters": CONFIGS[args.config].to_dict(),
        "results": results,
    }
    write_json(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
