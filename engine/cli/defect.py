"""``bonemesh defect``: the defect's template and measures (the library is ``engine.defect``).

    bonemesh defect SCAN [-o OUTDIR] [--voxel-size Z,Y,X] [--iso V | --preset bone [--hu-offset N]]
                    [--first-slice superior|inferior] [--flip-lr] [--flip-ap] [--hint-side left|right]
                    [--hint-point L,P,S] [--min-volume MM3] [--max-faces N] [--device ...]
    bonemesh defect --demo -o OUTDIR     (the bundled headsq head: no defect, a clear refusal)

Writes ``OUTDIR/implant.stl`` (binary STL, mm, the patient frame of ``model.stl``) and ``OUTDIR/defect.json``, and
prints a short summary. A scan without a one-sided defect, or with one across the midline, exits 2 with one line
(``NoDefectError``, ``MidlineDefectError``), and nothing is written. The default OUTDIR is ``SCAN``'s name with
``_defect``, beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

from engine.cli.args import (
    add_defect_args,
    add_level_args,
    add_orient_args,
    defect_params,
    orient_params,
    voxel_size_zyx,
)
from engine.errors import InputError
from engine.export.files import DEFECT_JSON, IMPLANT_STL


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``bonemesh defect`` on an ``argparse`` subparsers object (defaults from ``DefectParams``)."""
    p = subparsers.add_parser(
        "defect", help="the bone defect: its symmetry plane, size and a mirrored fill template (implant.stl)"
    )
    p.add_argument("input", nargs="?", help="slice archive or folder, DICOM series (zip or folder), TIFF or .npy")
    p.add_argument("-o", "--output", help="output folder (default: SCAN's name + _defect, beside it)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--voxel-size", dest="spacing", type=voxel_size_zyx, metavar="Z,Y,X",
                      help="voxel size in mm, z, y, x order, or named: z=1.5,y=0.5,x=0.5")  # fmt: skip
    size.add_argument("--spacing", dest="spacing", type=voxel_size_zyx, metavar="Z,Y,X", help="same as --voxel-size")
    add_level_args(p)
    add_orient_args(p)
    add_defect_args(p, command=True)
    p.add_argument("--device", default="auto", help="auto, cpu, cuda[:N] or opencl[:N] (default auto)")
    p.add_argument("--demo", action="store_true", help="use the bundled VTK headsq CT head")
    return p


def _output(args: argparse.Namespace) -> Path:
    if args.output:
        out = Path(args.output)
    elif args.input:
        src = Path(args.input)
        out = src.with_name(src.name.split(".")[0] + "_defect")
    else:
        raise InputError("give -o OUTDIR")
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out} is an existing file; give a folder for the outputs")
    return out


def run(args: argparse.Namespace) -> int:
    """``bonemesh defect``: find the defect on the scan as a job's model sees it (``engine.job.plans.prepare_volume``:
    the level, bone inside the body outline), as ``reconstruct --defect`` and a job with ``defect`` do, write its
    files, print the summary. Returns the exit code (0); a refusal (no defect, one across the midline, no symmetry)
    exits 2 with its reason."""
    from engine.cli.args import load_input
    from engine.defect.step import find_defect, measured_on
    from engine.job.plans import prepare_volume
    from engine.job.runtime import resolve_runtime
    from engine.params import IsoParams, ReconParams

    out = _output(args)
    params = defect_params(args)
    try:
        iso = IsoParams(iso=args.iso, preset=args.preset, hu_offset=args.hu_offset)
        runtime = resolve_runtime(args.device)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    volume, demo_level = load_input(args)
    orient = orient_params(args)
    if args.demo:
        from engine.data import HEADSQ_FIRST_SLICE

        orient = dataclasses.replace(orient, first_slice=HEADSQ_FIRST_SLICE)
        if args.iso is None and args.preset is None:
            iso = dataclasses.replace(iso, iso=demo_level)
    prepared = prepare_volume(volume, ReconParams(iso=iso, orient=orient))  # a job's defaults: as its model
    choice = prepared.choice
    on = measured_on(orient, dict(choice.report(prepared.volume.units)), prepared.body)
    t0 = time.perf_counter()
    outcome = find_defect(prepared.volume, params, choice.value, runtime.backend, orient, on)
    seconds = time.perf_counter() - t0
    if outcome.result is None:
        raise InputError((outcome.refusal or {}).get("message", "no defect found"))
    paths = _write(outcome.files(), out)
    _summary(json.loads(paths[DEFECT_JSON].read_bytes()), choice, paths, seconds)
    return 0


def _write(files: dict[str, bytes], out: Path) -> dict[str, Path]:
    """The defect's files into ``out``, each written beside and renamed (no partial file), in name order."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name in sorted(files, key=lambda n: n != IMPLANT_STL):  # implant.stl, then defect.json
        path = out / name
        tmp = path.with_name(f".{name}.part")
        tmp.write_bytes(files[name])
        os.replace(tmp, path)
        paths[name] = path
    return paths


def _summary(info: dict[str, Any], choice: Any, paths: dict[str, Path], seconds: float) -> None:
    plane, defect, implant = info["plane"], info["defect"], info["implant"]
    ext = defect["extent_lps_mm"]
    rows = [
        ("level", f"{choice.value:g} ({choice.how})"),
        ("plane", f"normal ({', '.join(f'{v:.4f}' for v in plane['normal_lps'])}), offset {plane['offset_mm']:.2f} mm, "
                  f"residual {plane['residual_mm']:.2f} mm"),
        ("defect", f"{defect['side']} side, {defect['volume_mm3']:,.0f} mm3, area {defect['area_mm2']:,.0f} mm2, "
                   f"slices {defect['slices'][0]}-{defect['slices'][1]}"),
        ("extent", f"{' x '.join(f'{v:.1f}' for v in ext['size'])} mm (LPS x, y, z), from "
                   f"({', '.join(f'{v:.1f}' for v in ext['min'])}) mm"),
        ("rim gap", f"{defect['rim']['gap_mm']:.2f} mm = {defect['rim']['gap_voxels']:.2f} voxels, contact "
                    f"{defect['rim']['contact_share']:.0%}"),
        ("implant", f"{implant['faces']:,} triangles, watertight {implant['watertight']}, {implant['components']} "
                    "piece(s), patient frame (LPS) mm"),
        ("time", f"{seconds:.2f} s"),
    ]  # fmt: skip
    rows += [(name, f"{path} ({path.stat().st_size:,} bytes)") for name, path in paths.items()]
    width = max(len(r[0]) for r in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")  # noqa: T201 - the command's summary table
