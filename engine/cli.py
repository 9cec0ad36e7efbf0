"""The ``bonemesh`` command line.

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

import numpy as np

from engine.errors import InputError


def _spacing(text: str) -> tuple[float, float, float]:
    try:
        parts = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected Z,Y,X in mm, got {text!r}") from None
    if len(parts) != 3 or not all(p > 0 for p in parts):
        raise argparse.ArgumentTypeError(f"expected three positive numbers Z,Y,X in mm, got {text!r}")
    return parts  # type: ignore[return-value]


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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "isosurface":
            return _isosurface(args)
    except InputError as exc:
        print(f"bonemesh: error: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    except Exception as exc:
        if os.environ.get("BONEMESH_DEBUG") == "1":
            raise
        print(f"bonemesh: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)  # noqa: T201
        return 1
    return 1
