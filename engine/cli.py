"""The ``bonemesh`` command line.

    bonemesh reconstruct INPUT -o OUTDIR [--iso V | --preset bone] [--spacing Z,Y,X] [--reduction R]
                         [--max-triangles N] [--iterations N] [--angle DEG] [--min-island-mm3 V] [--device ...]
    bonemesh reconstruct --demo -o OUTDIR
    bonemesh isosurface INPUT -o OUT.stl --iso LEVEL [--spacing Z,Y,X] [--device auto|cpu|cuda:N] [--open]
    bonemesh isosurface --demo -o OUT.stl

INPUT is a zip of 2-D slices (natural name order) or a ``.npy`` volume in (z, y, x) order. Exit codes: 0 done,
2 bad input (one-line reason on stderr, no output file), 1 internal error.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from engine.errors import InputError
from engine.params import ISO_PRESETS_HU


def _spacing(text: str) -> tuple[float, float, float]:
    try:
        parts = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected Z,Y,X in mm, got {text!r}") from None
    if len(parts) != 3 or not all(p > 0 for p in parts):
        raise argparse.ArgumentTypeError(f"expected three positive numbers Z,Y,X in mm, got {text!r}")
    return parts  # type: ignore[return-value]


def add_level_args(parser: argparse.ArgumentParser) -> None:
    """``--iso`` or ``--preset`` (with ``--hu-offset``): the iso level, for ``reconstruct`` and ``sweep``."""
    level = parser.add_mutually_exclusive_group()
    level.add_argument("--iso", type=float, help="iso level in the volume's units")
    level.add_argument("--preset", choices=sorted(ISO_PRESETS_HU), help="HU preset (bone = 300 HU)")
    parser.add_argument("--hu-offset", type=float, help="the stack stores HU + this offset (e.g. 1024), for --preset")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bonemesh", description="Bone surface models from CT slice stacks.")
    sub = parser.add_subparsers(dest="command", required=True)
    iso = sub.add_parser("isosurface", help="extract a Marching Cubes 33 surface and write a binary STL (mm)")
    iso.add_argument("input", nargs="?", help="zip of slice images, or a .npy volume (z, y, x)")
    iso.add_argument("-o", "--output", required=True, help="output .stl path")
    iso.add_argument("--iso", type=float, help="iso level in the volume's units")
    iso.add_argument("--spacing", type=_spacing, help="voxel size Z,Y,X in mm (required for slice stacks)")
    iso.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default auto)")
    iso.add_argument("--open", action="store_true", help="do not close the surface at the volume's borders")
    iso.add_argument("--demo", action="store_true", help="use the bundled VTK headsq CT head at its bone level")

    rec = sub.add_parser("reconstruct", help="the EMC33 pipeline: model.stl, model.glb, phone.glb, ar.glb, report")
    rec.add_argument("input", nargs="?", help="slice archive or folder, DICOM series (zip or folder), TIFF or .npy")
    rec.add_argument("-o", "--output", required=True, help="output folder")
    add_level_args(rec)
    rec.add_argument("--spacing", type=_spacing, help="voxel size Z,Y,X in mm (image stacks without it)")
    rec.add_argument("--reduction", type=float, help="fraction of faces kept by decimation (default 0.2)")
    rec.add_argument("--max-triangles", type=int, help="decimate to at most this many triangles instead")
    rec.add_argument("--iterations", type=int, default=1, help="Laplacian smoothing iterations (default 1)")
    rec.add_argument("--angle", type=float, default=0.5, help="smoothing threshold angle in degrees (default 0.5)")
    rec.add_argument("--min-island-mm3", type=float, help="drop pieces smaller than this volume")
    rec.add_argument("--keep-largest", type=int, help="keep only the N largest pieces")
    rec.add_argument("--open", action="store_true", help="do not close the surface at the volume's borders")
    rec.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default auto)")
    rec.add_argument("--demo", action="store_true", help="use the bundled VTK headsq CT head")
    rec.add_argument("--quiet", action="store_true", help="no progress bars")

    from engine.sweep import add_parser as add_sweep_parser

    add_sweep_parser(sub)
    return parser


def _load(args: argparse.Namespace) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    if args.demo:
        from engine.data import HEADSQ_BONE_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
        from engine.io.stack import load_slice_zip

        level = HEADSQ_BONE_LEVEL if args.iso is None else args.iso
        return load_slice_zip(HEADSQ_ZIP), level, args.spacing or HEADSQ_SPACING_ZYX_MM
    if not args.input:
        raise InputError("no INPUT given (or use --demo)")
    path = Path(args.input)
    if not path.is_file():
        raise InputError(f"{path} does not exist or is not a file")
    if args.iso is None:
        raise InputError("--iso LEVEL is required (the iso value in the volume's units)")
    if path.suffix.lower() == ".npy":
        try:
            volume = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise InputError(f"{path} is not a readable .npy array: {exc}") from None
    else:
        import zipfile

        from engine.io.stack import load_slice_zip

        if not zipfile.is_zipfile(path):
            raise InputError(f"{path} is neither a zip of slice images nor a .npy volume")
        try:
            volume = load_slice_zip(path)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    if args.spacing is None:
        raise InputError("--spacing Z,Y,X (mm) is required: the voxel size decides the model's size")
    return volume, args.iso, args.spacing


def _isosurface(args: argparse.Namespace) -> int:
    from engine.export.stl import to_stl
    from engine.isosurface import marching_cubes_33

    volume, level, spacing = _load(args)
    out = Path(args.output)
    if out.suffix.lower() != ".stl":
        raise InputError(f"expected an output path ending in .stl, got {out}")
    start = time.perf_counter()
    try:
        verts, faces = marching_cubes_33(volume, level, spacing=spacing, device=args.device, closed=not args.open)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    seconds = time.perf_counter() - start
    if len(faces) == 0:
        raise InputError(f"no surface at level {level}: the volume's values do not cross it")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(to_stl(verts, faces))
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    print(  # noqa: T201 - the command's report
        f"{out}: {len(verts):,} vertices, {len(faces):,} triangles from a {volume.shape} volume "
        f"at level {level} in {seconds:.2f} s"
    )
    return 0


def _recon_params(args: argparse.Namespace) -> Any:
    from engine.params import DecimateParams, IslandParams, IsoParams, ReconParams, SmoothParams

    try:
        decimate = DecimateParams(
            reduction=None if args.max_triangles else (args.reduction or 0.2), max_triangles=args.max_triangles
        )
        if args.reduction is not None and args.max_triangles is not None:
            raise ValueError("give --reduction or --max-triangles, not both")
        islands = None
        if args.min_island_mm3 is not None or args.keep_largest is not None:
            islands = IslandParams(min_volume_mm3=args.min_island_mm3, keep_largest=args.keep_largest)
        return ReconParams(
            iso=IsoParams(iso=args.iso, preset=args.preset, hu_offset=args.hu_offset, closed=not args.open),
            islands=islands,
            decimate=decimate,
            smooth=SmoothParams(iterations=args.iterations, angle_deg=args.angle),
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None


class _Bar:
    """One progress bar per stage on stderr."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.t0 = time.perf_counter()

    def __call__(self, stage: str, fraction: float) -> None:
        if self.quiet:
            return
        width = 30
        filled = round(fraction * width)
        sys.stderr.write(
            f"\r[{'#' * filled}{'.' * (width - filled)}] {fraction * 100:5.1f}%  {stage:<12s}"
            f" {time.perf_counter() - self.t0:7.2f} s"
        )
        if fraction >= 1.0:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _reconstruct(args: argparse.Namespace) -> int:
    from engine.io import load_volume
    from engine.pipeline import reconstruct, write_outputs

    params = _recon_params(args)
    if args.demo:
        from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

        volume = load_volume(HEADSQ_ZIP, spacing_zyx_mm=args.spacing or HEADSQ_SPACING_ZYX_MM)
        if args.iso is None and args.preset is None:
            import dataclasses

            params = dataclasses.replace(params, iso=dataclasses.replace(params.iso, iso=1150.0))
    else:
        if not args.input:
            raise InputError("no INPUT given (or use --demo)")
        if not Path(args.input).exists():
            raise InputError(f"{args.input} does not exist")
        volume = load_volume(args.input, spacing_zyx_mm=args.spacing)
    recon = reconstruct(volume, params, device=args.device, on_progress=_Bar(args.quiet))
    paths = write_outputs(recon, args.output, params, device=args.device)
    rep = recon.report
    rows = [
        ("input", f"{tuple(volume.data.shape)} {volume.data.dtype}, spacing {tuple(volume.spacing_zyx_mm)} mm"),
        ("iso level", f"{rep['iso_level']['value']:g} {rep['iso_level']['units']} ({rep['iso_level']['chosen_by']})"),
        ("device", rep["device"]["name"]),
    ]
    for stage, secs in rep["stage_seconds"].items():
        counts = rep["counts"].get(stage)
        extra = f"  {counts['faces']:,} faces" if isinstance(counts, dict) and "faces" in counts else ""
        rows.append((stage, f"{secs:8.3f} s{extra}"))
    mesh = rep["mesh"]
    rows.append(
        (
            "model",
            f"{mesh['n_faces']:,} faces, watertight {mesh['watertight']}, volume "
            f"{mesh['volume_mm3']:,.0f} mm3, area {mesh['area_mm2']:,.0f} mm2",
        )
    )
    for name, path in paths.items():
        rows.append((name, f"{path.stat().st_size:,} bytes"))
    width = max(len(r[0]) for r in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")  # noqa: T201 - the command's summary table
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "isosurface":
            return _isosurface(args)
        if args.command == "reconstruct":
            return _reconstruct(args)
        if args.command == "sweep":
            from engine.sweep import run as run_sweep

            return run_sweep(args)
    except InputError as exc:
        print(f"bonemesh: error: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    except Exception as exc:
        if os.environ.get("BONEMESH_DEBUG") == "1":
            raise
        print(f"bonemesh: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)  # noqa: T201
        return 1
    return 1
