"""Determinism fingerprints: SHA-256 of ``reconstruct``'s mesh and of the print model's bytes, per input and budget.

    python -m benchmarks.determinism --device cpu|cuda:0 [--phantom Z,Y,X] [--budgets none,256MiB] --out result.json

A refactor that claims "same meshes" shows it here: run the old and the new code on one device, in one call, and
compare the fingerprints (the mesh's vertex and face arrays, ``model.stl``). Inputs: the bundled headsq scan and
the bone phantom of ``benchmarks.phantom`` at ``--phantom`` (each with every budget: ``none`` runs the whole
volume at once, a size forces the streamed plan). Only stable public paths are imported (``engine.job.pipeline``,
``engine.job.outputs``, ``engine.params``, ``engine.types``, ``engine.io``), so the same script runs on old and new
checkouts.
"""

from __future__ import annotations

import argparse
import hashlib
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.phantom import bone_phantom
from benchmarks.report import write_json


def _inputs(phantom: tuple[int, int, int]) -> dict[str, tuple[Any, Any]]:
    from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
    from engine.io import load_volume
    from engine.params import IsoParams, ReconParams
    from engine.types import Volume

    headsq = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    ph = Volume(bone_phantom(phantom), (0.05, 0.05, 0.05), source={"generator": "benchmarks.phantom"})
    return {
        "headsq": (headsq, ReconParams(iso=IsoParams(iso=HEADSQ_LEVEL), body=None)),
        f"phantom_{'x'.join(map(str, phantom))}": (ph, ReconParams(iso=IsoParams(preset="bone", hu_offset=1024.0))),
    }


def fingerprint(volume: Any, params: Any, device: str, budget: str | None, files: bool = True) -> dict[str, Any]:
    """SHA-256 of the mesh (vertices, faces) and, with ``files``, of ``model.stl``; counts and the time taken."""
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    t0 = time.perf_counter()
    recon = reconstruct(volume, params, device=device, max_device_bytes=budget)
    seconds = time.perf_counter() - t0
    mesh = recon.mesh
    verts = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    stl = None
    if files:  # the exporters' dependencies (Draco, glTF, USD) may be absent where only the engine is installed
        with tempfile.TemporaryDirectory() as tmp:
            paths = write_outputs(recon, Path(tmp), params, device=device, max_device_bytes=budget)
            stl = hashlib.sha256(paths["model.stl"].read_bytes()).hexdigest()
    return {
        "budget": budget,
        "vertices": len(verts),
        "faces": len(faces),
        "mesh_sha256": hashlib.sha256(verts.tobytes() + faces.tobytes()).hexdigest(),
        "model_stl_sha256": stl,
        "reconstruct_seconds": round(seconds, 4),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--phantom", default="48,96,96", help="phantom shape Z,Y,X")
    parser.add_argument("--budgets", default="none,64MiB", help="comma-separated: none or a size (e.g. 256MiB)")
    parser.add_argument("--no-files", dest="files", action="store_false", help="hash the mesh only")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    phantom = tuple(int(v) for v in args.phantom.split(","))
    budgets = [None if b == "none" else b for b in args.budgets.split(",")]
    results: dict[str, Any] = {}
    for name, (volume, params) in _inputs(phantom).items():  # type: ignore[arg-type]
        results[name] = [fingerprint(volume, params, args.device, b, args.files) for b in budgets]
        for row in results[name]:
            print(name, row, flush=True)
    write_json(args.out, {"device": args.device, "phantom": list(phantom), "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
