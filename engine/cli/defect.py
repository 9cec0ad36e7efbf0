"""``bonemesh defect``: the defect's template and measures (the library is ``engine.defect``).

    bonemesh defect SCAN [-o OUTDIR] [--voxel-size Z,Y,X] [--iso V | --preset bone [--hu-offset N]]
                    [--first-slice superior|inferior] [--flip-lr] [--flip-ap] [--hint-side left|right]
                    [--hint-point X,Y,Z] [--min-volume MM3] [--max-faces N] [--device ...]
    bonemesh defect --demo -o OUTDIR     (the bundled headsq head: no defect, a clear refusal)

Writes ``OUTDIR/implant.stl`` (binary STL, mm, the patient frame of ``model.stl``) and ``OUTDIR/defect.json``, and
prints a short summary. A scan without a one-sided defect, or with one across the midline, exits 2 with one line
(``NoDefectError``, ``MidlineDefectError``), and nothing is written. The default OUTDIR is ``SCAN``'s name with
``_defect``, beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path
from typing import Any

from engine.cli.args import add_level_args, add_orient_args, orient_params, voxel_size_zyx
from engine.errors import InputError


def _point(text: str) -> tuple[float, float, float]:
    try:
        vals = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm (patient frame, LPS), got {text!r}") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected three finite numbers X,Y,Z in mm, got {text!r}")
    return vals  # type: ignore[return-value]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``bonemesh defect`` on an ``argparse`` subparsers object (defaults from ``DefectParams``)."""
    from engine.defect.params import DEFAULT_MAX_FACES, SIDES

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
    p.add_argument("--hint-side", choices=SIDES, help="the defect is on the patient's left or right")
    p.add_argument("--hint-point", type=_point, metavar="X,Y,Z",
                   help="a point in or next to the defect, patient frame (LPS) mm")  # fmt: skip
    p.add_argument("--min-volume", type=float, metavar="MM3", help="smallest defect reported (default: the rule)")
    p.add_argument("--max-faces", type=int, default=DEFAULT_MAX_FACES,
                   help="decimate the implant to at most this many triangles (default %(default)s)")  # fmt: skip
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
    """``bonemesh defect``: find the defect, write its files, print the summary. Returns the exit code (0)."""
    from engine.cli.args import load_input
    from engine.defect import DefectParams, write_defect
    from engine.defect import run as find_defect
    from engine.level import resolve_level
    from engine.params import IsoParams, ReconParams

    out = _output(args)
    try:
        params = DefectParams(
            side=args.hint_side, point_lps_mm=args.hint_point, min_volume_mm3=args.min_volume, max_faces=args.max_faces
        )
        iso = IsoParams(iso=args.iso, preset=args.preset, hu_offset=args.hu_offset)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    volume, demo_level = load_input(args)
    orient = orient_params(args)
    if args.demo:
        from engine.data import HEADSQ_FIRST_SLICE

        orient = dataclasses.replace(orient, first_slice=HEADSQ_FIRST_SLICE)
        if args.iso is None and args.preset is None:
            iso = dataclasses.replace(iso, iso=demo_level)
    choice = resolve_level(volume, ReconParams(iso=iso, orient=orient))
    t0 = time.perf_counter()
    result = find_defect(volume, params, choice.value, args.device, orient=orient)
    seconds = time.perf_counter() - t0
    paths = write_defect(result, out)
    _summary(result.to_json(), choice, paths, seconds)
    return 0


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
