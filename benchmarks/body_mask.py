"""The body mask's seconds (``engine.volume.bodymask.isolate_bone``: bone of the body only, the default for every HU
scan): the real scans of ../shared/data (when present) and a synthetic clinical CT of a given size, each timed in a
process of its own; with ``--before TREE`` the same inputs through another checkout's code in the same run, the
ratio before/after per input and whether the two give the same volume and report.

The synthetic CT (HU, int16): an elliptic body of soft tissue with a skull-like bone ring inside, resting on a
couch plate, and a holder plate in the air beside it (what the mask removes), at ``--shape`` (default a
400 x 512 x 512 CT, 105 M voxels).

    python -m benchmarks.body_mask --shape 400,512,512 --repeat 3 [--before /tmp/before] \
        --out benchmarks/results/body_mask_cpu.json
    python -m benchmarks.body_mask --shape 8,32,32 --repeat 1 --data /nowhere --out /tmp/b.json   # smoke
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.report import write_json

REPO = Path(__file__).resolve().parents[1]
SCANS = {  # name: (path under the data folder, spacing for a stack (None: the DICOM's), level, HU offset)
    "cranium_ct": ("cranium_ct/cranium_ct_png16.zip", (1.5, 0.957, 0.957), 1324.0, 1024.0),
    "gantry_tilt": ("gantry_tilt_dicom/gantry_tilt_dicom.zip", None, 300.0, 0.0),
    "head_phantom": ("head_phantom_dicom/head_phantom_dicom.zip", None, 300.0, 0.0),
    "pelvis_ct": ("pelvis_ct/pelvis_ct_png16.zip", (5.0, 1.663, 1.663), 1324.0, 1024.0),
}

# run in a fresh interpreter with the checkout to time on its path (the code before has no copy of this module)
TIMER = r"""
import hashlib, json, sys, time
import numpy as np
from engine.params import BodyMaskParams
from engine.types import Volume
from engine.volume.bodymask import isolate_bone
path, spacing, repeat = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[5])
level, offset = float(sys.argv[3]), float(sys.argv[4])
vol = Volume(np.load(path), tuple(spacing), units="HU")
seconds = []
for _ in range(repeat):
    t0 = time.perf_counter()
    out, info = isolate_bone(vol, level, BodyMaskParams(), offset)
    seconds.append(time.perf_counter() - t0)
info.pop("seconds", None)
digest = hashlib.sha256(np.ascontiguousarray(out.data).tobytes()).hexdigest()
print(json.dumps({"seconds": seconds, "result_sha256": digest, "info": info}))
"""


def clinical_ct(shape: tuple[int, int, int]) -> np.ndarray:
    """A synthetic HU CT of ``shape`` (see the module docstring)."""
    nz, ny, nx = shape
    y, x = np.ogrid[:ny, :nx]
    r = np.hypot((y - 0.45 * ny) / (0.36 * ny), (x - 0.5 * nx) / (0.3 * nx))
    plane = np.full((ny, nx), -1000, np.int16)
    plane[r < 1] = 40
    plane[(r > 0.55) & (r < 0.72)] = 900
    couch = int(0.81 * ny)
    plane[couch : couch + max(1, ny // 40), nx // 16 : nx - nx // 16] = 600
    plane[int(0.3 * ny) : int(0.6 * ny), int(0.9 * nx) : int(0.9 * nx) + max(1, nx // 50)] = 1000
    out = np.broadcast_to(plane, shape).copy()
    out[: max(1, nz // 20)] = -1000  # air above and below the body
    out[nz - max(1, nz // 20) :] = -1000
    return out


def _time(tree: Path, npy: Path, spacing: Any, level: float, offset: float, repeat: int) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    args = [sys.executable, "-c", TIMER, str(npy), json.dumps(list(spacing)), str(level), str(offset), str(repeat)]
    done = subprocess.run(args, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    row: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    row["median_seconds"] = float(np.median(row["seconds"]))
    return row


def _inputs(data: Path, shape: tuple[int, int, int], work: Path) -> dict[str, tuple[Path, Any, float, float, str]]:
    """Each input saved as .npy: name -> (file, spacing, level, HU offset, what it is)."""
    from engine.io import load_volume

    out = {}
    for name, (rel, spacing, level, offset) in SCANS.items():
        path = data / rel
        if not path.exists():
            print(f"{name}: {path} is absent, skipped")
            continue
        vol = load_volume(path, **({"spacing_zyx_mm": spacing} if spacing else {}))
        np.save(work / f"{name}.npy", vol.data)
        out[name] = (work / f"{name}.npy", vol.spacing_zyx_mm, level, offset, f"{list(vol.data.shape)} {path.name}")
    name = "clinical_" + "x".join(map(str, shape))
    np.save(work / f"{name}.npy", clinical_ct(shape))
    pixel = 400.0 / shape[2]  # a 400 mm field of view, 1 mm slices
    out[name] = (work / f"{name}.npy", (1.0, pixel, pixel), 300.0, 0.0, "synthetic HU CT, couch and holder")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--shape", default="400,512,512", help="Z,Y,X of the synthetic CT")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--before", type=Path, default=None, metavar="TREE", help="a checkout of the code before")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    shape = tuple(int(s) for s in args.shape.split(","))
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bonemesh-bodymask-") as tmp:
        for name, (npy, spacing, level, offset, what) in _inputs(args.data, shape, Path(tmp)).items():  # type: ignore[arg-type]
            row: dict[str, Any] = {"input": what, "after": _time(REPO, npy, spacing, level, offset, args.repeat)}
            if args.before is not None:
                row["before"] = _time(args.before, npy, spacing, level, offset, args.repeat)
                a, b = row["after"], row["before"]
                if "error" not in a and "error" not in b:
                    row["ratio_before_over_after"] = round(b["median_seconds"] / a["median_seconds"], 3)
                    row["same_result"] = a["result_sha256"] == b["result_sha256"] and a["info"] == b["info"]
            results[name] = row
            print(name, json.dumps({k: v for k, v in row.items() if k != "input"})[:300], flush=True)
    report = {
        "benchmark": "body_mask",
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "repeat": args.repeat,
        "before": str(args.before) if args.before else None,
        "results": results,
    }
    write_json(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
