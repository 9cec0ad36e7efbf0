"""Viewing-copy benchmark: the phone and AR copies of ``engine.job.outputs`` (issue 9) on the bone phantom.

    python -m benchmarks.viewing_copies --device cpu|cuda:0 [--phantom Z,Y,X] [--budgets PHONE,AR ...]
                                        [--repeat N] [--quality] --out result.json

The phantom (``benchmarks.phantom``, default 238x512x512) is reconstructed once with the paper's defaults (kernels
compiled first on its central slices). For each pair of budgets (default: the product's 100,000 and 50,000; on a
reduced phantom, budgets scaled down with the mesh show the full phantom's behaviour): the print model laid out as
``write_outputs`` does, then ``viewing_copies`` timed N times (median; passes, faces and routes do not depend on
the device), the copies' topology (device mesh statistics) and, with ``--quality``, their surface distance to the
print model (``engine.paper.metrics.DistanceReference``); then ``write_outputs`` with those budgets, N times (median,
with its parts: ``layout_kernels`` and ``layout_copies`` split the layout). On a checkout without ``viewing_copies``
(before issue 9's viewing-copy routes) the copies are made as ``write_outputs`` made them there.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.phantom import bone_phantom
from benchmarks.report import write_json
from engine.params import ExportParams, IsoParams, ReconParams
from engine.types import Volume

PAPER = ReconParams(iso=IsoParams(preset="bone", hu_offset=1024.0), body=None, islands=None)
TOPOLOGY = ("n_faces", "watertight", "manifold", "components", "euler", "boundary_edges", "nonmanifold_edges")


def _copies(pos: Any, faces: Any, budgets: list[int], pieces: int | None, closed: bool) -> list[tuple]:
    import engine.job.outputs as eo

    if hasattr(eo, "viewing_copies"):
        return eo.viewing_copies(pos, faces, budgets, pieces, closed)
    phone = eo.viewing_copy(pos, faces, budgets[0], pieces, closed)  # the route before viewing_copies
    return [phone, eo.viewing_copy(phone[0], phone[1], budgets[1])]


def _budget_run(recon: Any, lay: Any, device: str, budgets: list[int], repeat: int, quality: Any) -> dict[str, Any]:
    import warp as wp

    from engine.job.outputs import write_outputs
    from engine.surface.devmesh import mesh_stats_device

    stats = recon.report["mesh"]
    closed = bool(stats["watertight"]) and bool(stats["manifold"])
    runs = []
    with wp.ScopedDevice(device):
        for _ in range(repeat):
            wp.synchronize_device()
            t0 = time.perf_counter()
            copies = _copies(lay.view_pos, lay.faces, budgets, stats["components"], closed)
            wp.synchronize_device()
            runs.append(time.perf_counter() - t0)
        out: dict[str, Any] = {"viewing_copies_seconds": float(np.median(runs)), "viewing_copies_seconds_all": runs}
        for name, (p, f, summary) in zip(("phone", "ar"), copies, strict=True):
            entry = {"summary": summary, "topology": {k: mesh_stats_device(p, f)[k] for k in TOPOLOGY}}
            if quality is not None:
                entry["distance_to_print_model"] = quality.compare(p.numpy(), f.numpy())
            out[name] = entry
    params = dataclasses.replace(
        PAPER, export=ExportParams(phone_max_triangles=budgets[0], ar_max_triangles=budgets[1])
    )
    writes = []
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_outputs(recon, tmp, params, device=device)
            writes.append((time.perf_counter() - t0, recon.report["write_seconds"]))
    writes.sort(key=lambda w: w[0])
    out["write_outputs_seconds"], out["write_outputs_parts"] = writes[len(writes) // 2]
    out["write_outputs_seconds_all"] = [w[0] for w in writes]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--phantom", default="238,512,512", help="phantom shape Z,Y,X")
    parser.add_argument("--budgets", nargs="+", default=["100000,50000"], help="PHONE,AR face budgets (pairs)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quality", action="store_true", help="surface distance of each copy to the print model")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from engine.device import resolve_device
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    device = str(resolve_device(args.device))
    shape = tuple(int(s) for s in args.phantom.split(","))
    volume = Volume(bone_phantom(shape), (0.05, 0.05, 0.05), source={"generator": "benchmarks.phantom"})
    nz = shape[0]
    warm = dataclasses.replace(volume, data=volume.data[nz // 2 - min(24, nz // 2) : nz // 2 + min(24, nz // 2)])
    with tempfile.TemporaryDirectory() as tmp:  # kernel compilation
        write_outputs(reconstruct(warm, PAPER, device=device), tmp, PAPER, device=device)
    t0 = time.perf_counter()
    recon = reconstruct(volume, PAPER, device=device)
    seconds = time.perf_counter() - t0
    mesh = recon.report["mesh"]
    print(f"[viewing_copies] {shape}: {mesh['n_faces']:,} faces, {mesh['components']:,} pieces, ", end="")
    print(f"Euler {mesh['euler']:,}; reconstruct {seconds:.2f} s", flush=True)
    import warp as wp

    from engine.job.outputs import lay_out
    from engine.orient import Frame

    with wp.ScopedDevice(device):  # the print model as write_outputs lays it out (the viewing copies' frame)
        lay = lay_out(*recon.device_mesh, Frame.from_dict(recon.report.get("frame")))
    quality = None
    if args.quality:
        from engine.paper.metrics import DistanceReference

        quality = DistanceReference(lay.view_pos.numpy(), lay.faces.numpy(), device=device)
    results = {}
    for pair in args.budgets:
        budgets = [int(b) for b in pair.split(",")]
        r = results[pair] = _budget_run(recon, lay, device, budgets, args.repeat, quality)
        line = ", ".join(
            f"{name} {r[name]['summary']['faces']:,} faces {r[name]['summary'].get('passes', 0)} passes"
            f" topology_preserved {r[name]['summary'].get('topology_preserved', True)}"
            for name in ("phone", "ar")
        )
        print(f"  budgets {pair}: copies {r['viewing_copies_seconds']:.3f} s ({line});", end=" ")
        print(f"write_outputs {r['write_outputs_seconds']:.3f} s", flush=True)
    report = {
        "benchmark": "viewing_copies",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "device": device,
        "phantom": list(shape),
        "timing": f"median of {args.repeat} after a warm-up on the central slices",
        "reconstruct_seconds": seconds,
        "mesh": mesh,
        "results": results,
    }
    write_json(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
