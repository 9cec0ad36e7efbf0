"""Decimation benchmark: the Warp kernels against MeshLab on the same MC33 meshes, speed and quality.

    python -m benchmarks.decimate --device cpu|cuda:0 [--data ../shared/data] [--scans cranium_ct,...]
                                  [--phantom Z,Y,X] [--reductions 0.2,0.5] [--repeat N] [--no-meshlab]
                                  --out result.json

Each input goes through the paper's front end (3x3x3 Gaussian, MC33 closed at the bone level) on the device; the
MC33 mesh is then decimated (a) by ``engine.decimation.passes.decimate_device`` on the device where it already is
(warm-up on the first input, then the median of ``repeat`` runs; peak device memory from the CUDA mempool), and
(b) by MeshLab's quadric collapse (``method="meshlab"``: CPU processes, as the pipeline used to). Both results are
checked (watertight, manifold, components and Euler characteristic against the MC33 mesh, folds) and measured
against the undecimated surface (mean / p95 / Hausdorff distance, both ways, ``engine.paper.metrics``), with triangle
shape (smallest angles). Ratios Warp/MeshLab come from the same run.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

# name: (zip, spacing zyx mm, level in stored units)
SCANS = {
    "cranium_ct": ("cranium_ct_png16.zip", (1.5, 0.9570312, 0.9570312), 1324.0),
    "pelvis_ct": ("pelvis_ct_png16.zip", (5.0, 1.663, 1.663), 1324.0),
    "head_phantom_dicom": ("head_phantom_png16.zip", (5.0, 0.451, 0.451), 1324.0),
    "shrew_trabecular_microct": ("shrew_trabecular_png16.zip", (0.0041, 0.0041, 0.0041), 127.5),
}


def _mc33(data: np.ndarray, spacing: tuple[float, float, float], level: float, dev: Any) -> tuple[Any, Any]:
    import warp as wp

    from engine.isosurface import extract_isosurface
    from engine.params import GaussianParams
    from engine.volume.gaussian import smooth_volume

    field = smooth_volume(wp.array(np.ascontiguousarray(data), device=dev), GaussianParams())
    v, f = extract_isosurface(field, level, spacing=spacing, closed=True)
    del field
    return wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i)


def _check(v: np.ndarray, f: np.ndarray, ref: dict[str, Any] | None) -> dict[str, Any]:
    from engine.paper.metrics import min_angles_deg
    from engine.surface.meshcheck import folds, mesh_stats

    s = mesh_stats(v, f)
    ang = min_angles_deg(v, f)
    out = {
        "faces": len(f),
        "vertices": len(v),
        "watertight": s["watertight"],
        "manifold": s["manifold"],
        "components": s["components"],
        "euler": s["euler"],
        "volume_mm3": s["volume_mm3"],
        "folds": folds(v[:, ::-1].astype(np.float64), f),
        "min_angle_p5_deg": float(np.percentile(ang, 5)),
        "below_10deg": float(np.mean(ang < 10)),
    }
    if ref is not None:
        out["same_topology"] = (s["components"], s["euler"]) == (ref["components"], ref["euler"])
        out["volume_change_pct"] = 100 * (s["volume_mm3"] / ref["volume_mm3"] - 1)
    return out


def _similarity(v: np.ndarray, f: np.ndarray, scan: tuple[np.ndarray, tuple[float, float, float], float], n: int):
    """The paper's RMSE % and SSIM % (and Dice) of the mesh's sections against the scan's slices at the level."""
    from engine.paper.metrics import slice_similarity

    data, spacing, level = scan
    out = slice_similarity(v, f, data, level, spacing, max_slices=n)
    return {k: out[k] for k in ("rmse_pct", "ssim_pct", "dice")} | {"slices_compared": len(out["slices"])}


def _one(name: str, pos: Any, faces: Any, reductions: list[float], args: argparse.Namespace, dev: Any, scan) -> dict:
    import warp as wp

    from benchmarks.mc33 import _DeviceMemory
    from engine.decimation import decimate_device, decimate_mesh
    from engine.paper.metrics import DistanceReference

    v_in, f_in = pos.numpy(), faces.numpy().astype(np.int32)
    print(f"{name}: MC33 {len(f_in):,} faces", flush=True)
    ref = _check(v_in, f_in, None)
    if args.slices:
        ref["similarity"] = _similarity(v_in, f_in, scan, args.slices)
    dist = DistanceReference(v_in, f_in, n_points=args.points, device=str(dev))
    rows = []
    for r in reductions:
        target = max(1, round(r * len(f_in)))
        times, mem = [], _DeviceMemory(dev)
        mem.start()
        for _ in range(args.repeat):
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            p, f, st = decimate_device(pos, faces, target)
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t0)
        row: dict[str, Any] = {"reduction": r, "target_faces": target}
        wv, wf = p.numpy(), f.numpy().astype(np.int32)
        warp_row = {
            "seconds": statistics.median(times),
            "seconds_all": times,
            "input_faces_per_s": len(f_in) / statistics.median(times),
            "passes": st.passes,
            "stopped": st.stopped,
            "collapses_per_pass": st.collapses,
            **mem.result(),
            **_check(wv, wf, ref),
            "distance": dist.compare(wv, wf),
        }
        if args.slices:
            warp_row["similarity"] = _similarity(wv, wf, scan, args.slices)
        row["warp"] = warp_row
        print(f"  R={r}: warp {warp_row['seconds']:.3f} s, {len(wf):,} faces, {st.passes} passes, "
              f"mean {warp_row['distance']['mean_mm']:.5f} mm", flush=True)  # fmt: skip
        if args.meshlab:
            t0 = time.perf_counter()
            mv, mf, info = decimate_mesh(v_in, f_in, max_triangles=len(wf), method="meshlab")
            ml = {"seconds": time.perf_counter() - t0, "workers": info.get("workers"), **_check(mv, mf, ref)}
            ml["distance"] = dist.compare(mv, mf)
            if args.slices:
                ml["similarity"] = _similarity(mv, mf, scan, args.slices)
            row["meshlab"] = ml
            row["ratios"] = {
                "speedup": ml["seconds"] / warp_row["seconds"],
                "mean_distance_warp_over_meshlab": warp_row["distance"]["mean_mm"] / ml["distance"]["mean_mm"],
                "hausdorff_warp_over_meshlab": warp_row["distance"]["hausdorff_mm"] / ml["distance"]["hausdorff_mm"],
            }
            print(f"         meshlab {ml['seconds']:.2f} s, {len(mf):,} faces, mean {ml['distance']['mean_mm']:.5f}"
                  f" mm", flush=True)  # fmt: skip
        if args.profile:
            _, _, stp = decimate_device(pos, faces, target, profile=True)
            row["warp"]["profile_seconds"] = stp.profile
            print(f"         profile {stp.profile}", flush=True)
        rows.append(row)
    return {"mc33": ref, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--scans", default=",".join(SCANS))
    ap.add_argument("--phantom", default=None, help="Z,Y,X of the bone phantom (HU + 1024)")
    ap.add_argument("--reductions", default="0.2,0.5")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--points", type=int, default=400_000, help="surface samples each way for the distances")
    ap.add_argument("--no-meshlab", dest="meshlab", action="store_false")
    ap.add_argument("--slices", type=int, default=64, help="slices for the RMSE/SSIM comparison (0: none)")
    ap.add_argument("--profile", action="store_true", help="one more run, synchronised per step, timed per step")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    import warp as wp

    from engine.decimation.passes import decimate_device
    from engine.device import resolve_device
    from engine.io.stack import load_slice_zip
    from engine.job.pipeline import _versions

    dev = resolve_device(args.device)
    reductions = [float(x) for x in args.reductions.split(",")]
    inputs: list[tuple[str, Any]] = []
    for name in [s for s in args.scans.split(",") if s]:
        zipname, spacing, level = SCANS[name]
        path = Path(args.data) / name / zipname
        if path.exists():
            inputs.append((name, lambda p=path, s=spacing, lv=level: (load_slice_zip(p), s, lv)))
        else:
            print(f"{name}: skipped ({path} is absent)")
    if args.phantom:
        from benchmarks.phantom import bone_phantom

        shape = tuple(int(x) for x in args.phantom.split(","))
        inputs.append((f"phantom_{'x'.join(map(str, shape))}", lambda: (bone_phantom(shape), (0.05,) * 3, 1324.0)))
    result: dict[str, Any] = {
        "benchmark": "decimate",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "device": {"spec": args.device, "name": str(dev), "description": getattr(dev, "name", str(dev))},
        "host": {"machine": platform.machine(), "processor": platform.processor()},
        "versions": _versions(),
        "inputs": {},
    }
    with wp.ScopedDevice(dev):
        warm = _mc33(np.pad(np.full((12, 12, 12), 2000, np.uint16), 2), (1.0, 1.0, 1.0), 1324.0, dev)
        decimate_device(*warm, 10)  # compile the kernels
        for name, load in inputs:
            data, spacing, level = load()
            pos, faces = _mc33(data, spacing, level, dev)
            result["inputs"][name] = _one(name, pos, faces, reductions, args, dev, (data, spacing, level))
            del data
            Path(args.out).write_text(json.dumps(result, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
