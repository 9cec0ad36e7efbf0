"""Argument parsing shared by the ``bonemesh`` commands: voxel size, level, orientation, pipeline options.

Every default comes from the parameter dataclasses (``engine.params``), so the CLI, the Python API and the job
parameters cannot drift apart. Only the CLI modules import this one.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from engine.errors import InputError
from engine.params import (
    FIRST_SLICE_CHOICES,
    ISO_PRESETS_HU,
    BodyMaskParams,
    DecimateParams,
    IslandParams,
    IsoParams,
    OrientParams,
    PreprocessParams,
    ReconParams,
    SmoothParams,
)
from engine.types import Volume

if TYPE_CHECKING:
    from engine.budget import Budget

Spacing = tuple[float, float, float]


def default(kind: type, name: str) -> Any:
    """The default of a parameter dataclass's field (for argparse defaults and help texts)."""
    for f in dataclasses.fields(kind):
        if f.name == name:
            return f.default
    raise KeyError(f"{kind.__name__} has no field {name!r}")


def _axes(text: str, order: str) -> Spacing:
    """Three positive mm values given in ``order`` ("zyx" or "xyz"), or named (``x=0.9,y=0.9,z=1.5``, any order);
    returned as (z, y, x)."""
    parts = [p.strip() for p in text.split(",")]
    example = "Z,Y,X" if order == "zyx" else "X,Y,Z"
    try:
        if any("=" in p for p in parts):
            named = {}
            for p in parts:
                key, _, value = p.partition("=")
                named[key.strip().lower()] = float(value)
            if sorted(named) != ["x", "y", "z"]:
                raise ValueError
            vals = (named["z"], named["y"], named["x"])
        else:
            nums = tuple(float(p) for p in parts)
            if len(nums) != 3:
                raise ValueError
            vals = nums if order == "zyx" else nums[::-1]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected three numbers {example} in mm, or named axes x=..,y=..,z=.., got {text!r}"
        ) from None
    if not all(math.isfinite(v) and v > 0 for v in vals):
        raise argparse.ArgumentTypeError(f"expected three positive voxel sizes in mm, got {text!r}")
    return vals  # type: ignore[return-value]


def spacing_zyx(text: str) -> Spacing:
    """``--spacing Z,Y,X`` (the engine's array order), or named axes."""
    return _axes(text, "zyx")


def voxel_size_xyz(text: str) -> Spacing:
    """``--voxel-size X,Y,Z`` (the order of most tools and of the datasets' READMEs), or named; returns (z, y, x)."""
    return _axes(text, "xyz")


def describe_voxel_size(spacing: Spacing) -> str:
    """The voxel size with its axes named, so that the order cannot be misread."""
    z, y, x = spacing
    return f"x {x:g} mm, y {y:g} mm, z {z:g} mm (x: image columns, y: image rows, z: slices)"


def add_input_args(parser: argparse.ArgumentParser, what: str) -> None:
    """INPUT, ``-o``, the voxel size (two unmisreadable forms) and the device."""
    parser.add_argument("input", nargs="?", help="slice archive or folder, DICOM series (zip or folder), TIFF or .npy")
    parser.add_argument("-o", "--output", required=True, help=what)
    size = parser.add_mutually_exclusive_group()
    size.add_argument(
        "--voxel-size", dest="spacing", type=voxel_size_xyz, metavar="X,Y,Z",
        help="voxel size in mm in x, y, z order (x: image columns, y: rows, z: slice step), or x=..,y=..,z=..",
    )  # fmt: skip
    size.add_argument(
        "--spacing", dest="spacing", type=spacing_zyx, metavar="Z,Y,X",
        help="the same in z, y, x order (array order), or z=..,y=..,x=..",
    )  # fmt: skip
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default auto)")
    parser.add_argument(
        "--max-device-bytes", type=_budget, default=None, metavar="SIZE",
        help="device memory budget, e.g. 2GiB: every stage keeps to it (the volume streams in slabs; a large mesh "
        "is decimated piece by piece); default none",
    )  # fmt: skip


def _budget(text: str) -> Budget:
    """``--max-device-bytes``, parsed once here: the ``Budget`` that ``reconstruct`` and ``write_outputs`` share."""
    from engine.budget import Budget

    try:
        return Budget.of(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_level_args(parser: argparse.ArgumentParser) -> None:
    """``--iso`` or ``--preset`` (with ``--hu-offset``): the iso level."""
    level = parser.add_mutually_exclusive_group()
    level.add_argument("--iso", type=float, help="iso level in the volume's units")
    level.add_argument("--preset", choices=sorted(ISO_PRESETS_HU), help="HU preset (bone = 300 HU)")
    parser.add_argument("--hu-offset", type=float, help="the stack stores HU + this offset (e.g. 1024), for --preset")


def add_orient_args(parser: argparse.ArgumentParser) -> None:
    """How an image stack lies in the patient (DICOM ignores these: its headers say it)."""
    parser.add_argument(
        "--first-slice", choices=FIRST_SLICE_CHOICES, default=default(OrientParams, "first_slice"),
        help="image stacks: which end of the patient the first slice is (default %(default)s)",
    )  # fmt: skip
    parser.add_argument("--flip-lr", action="store_true", help="image stacks: the image's left is the patient's left")
    parser.add_argument("--flip-ap", action="store_true", help="image stacks: the image's top is posterior")


def add_recon_args(parser: argparse.ArgumentParser) -> None:
    """The pipeline's options for ``reconstruct`` (defaults from the dataclasses)."""
    add_level_args(parser)
    add_orient_args(parser)
    r, it = default(DecimateParams, "reduction"), default(SmoothParams, "iterations")
    ang = default(SmoothParams, "angle_deg")
    parser.add_argument("--reduction", type=float, help=f"fraction of faces kept by decimation (default {r:g})")
    parser.add_argument("--max-triangles", type=int, help="decimate to at most this many triangles instead")
    parser.add_argument("--iterations", type=int, default=it, help=f"Laplacian smoothing iterations (default {it})")
    parser.add_argument("--angle", type=float, default=ang, help=f"smoothing threshold angle, deg (default {ang:g})")
    vox = default(IslandParams, "min_volume_voxels")
    parser.add_argument("--min-island-mm3", type=float, help=f"drop pieces below this volume (default {vox:g} voxels)")
    parser.add_argument("--keep-largest", type=int, help="keep only the N largest pieces")
    parser.add_argument("--keep-specks", action="store_true", help="keep pieces of any size (no speck removal)")
    parser.add_argument(
        "--keep-outside-body", action="store_true",
        help="HU data: keep bone-level pieces outside the body outline (couch, head holder)",
    )  # fmt: skip
    parser.add_argument(
        "--outline-hu", type=float, default=default(BodyMaskParams, "outline_hu"),
        help="HU data: the body outline's air/tissue threshold (default %(default)g HU)",
    )  # fmt: skip
    pre = parser.add_argument_group("slice preprocessing (the paper's; order: threshold, area opening, Canny)")
    pre.add_argument("--threshold", type=float, help="set samples below this value to the volume's minimum")
    pre.add_argument("--area-opening-px", type=int, help="remove bright specks below this many pixels per slice")
    pre.add_argument("--canny-sigma", type=float, help="replace each slice by its Canny edge map with this sigma")
    parser.add_argument("--open", action="store_true", help="do not close the surface at the volume's borders")


def recon_params(args: argparse.Namespace) -> ReconParams:
    """The ``ReconParams`` of ``reconstruct``'s arguments; an option left out keeps the dataclass default.

    Raises:
        InputError: an invalid value or combination (exit code 2).
    """
    try:
        if args.reduction is not None and args.max_triangles is not None:
            raise ValueError("give --reduction or --max-triangles, not both")
        if args.max_triangles is not None:
            decimate = DecimateParams(reduction=None, max_triangles=args.max_triangles)
        elif args.reduction is not None:
            decimate = DecimateParams(reduction=args.reduction)
        else:
            decimate = DecimateParams()
        islands: IslandParams | None = IslandParams(min_volume_mm3=args.min_island_mm3, keep_largest=args.keep_largest)
        if args.keep_specks:
            if args.min_island_mm3 is not None:
                raise ValueError("give --keep-specks or --min-island-mm3, not both")
            islands = None
            if args.keep_largest is not None:
                islands = IslandParams(keep_largest=args.keep_largest, min_volume_voxels=None)
        preprocess = None
        if args.threshold is not None or args.canny_sigma is not None or args.area_opening_px is not None:
            preprocess = PreprocessParams(
                threshold=args.threshold, canny_sigma=args.canny_sigma, area_opening_px=args.area_opening_px
            )
        return ReconParams(
            preprocess=preprocess,
            iso=IsoParams(iso=args.iso, preset=args.preset, hu_offset=args.hu_offset, closed=not args.open),
            islands=islands,
            decimate=decimate,
            smooth=SmoothParams(iterations=args.iterations, angle_deg=args.angle),
            orient=orient_params(args),
            body=None if args.keep_outside_body else BodyMaskParams(outline_hu=args.outline_hu),
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None


def orient_params(args: argparse.Namespace) -> OrientParams:
    """The stack orientation of the arguments."""
    return OrientParams(first_slice=args.first_slice, flip_lr=args.flip_lr, flip_ap=args.flip_ap)


def output_folder(path: str) -> Path:
    """``-o`` for commands that write a folder: refused (exit 2) when it names an existing file."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out} is an existing file; give a folder for the outputs")
    return out


def output_file(path: str, suffix: str) -> Path:
    """``-o`` for commands that write one file: the suffix is checked, and an existing folder refused."""
    out = Path(path)
    if out.suffix.lower() != suffix:
        raise InputError(f"expected an output path ending in {suffix}, got {out}")
    if out.is_dir():
        raise InputError(f"-o {out} is an existing folder; give a {suffix} file path")
    return out


def load_input(args: argparse.Namespace, on_progress: Callable[[float], None] | None = None) -> tuple[Volume, float]:
    """The one input loader of the commands: INPUT through ``engine.io.load_volume``, or ``--demo`` (the bundled
    headsq CT head with its voxel size). Also the demo's bone level (NaN for other inputs).

    Raises:
        InputError: no INPUT, a missing path, or what ``load_volume`` refuses.
    """
    from engine.io import load_volume

    if getattr(args, "demo", False):
        from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

        spacing = args.spacing or HEADSQ_SPACING_ZYX_MM
        return load_volume(HEADSQ_ZIP, spacing_zyx_mm=spacing, on_progress=on_progress), HEADSQ_LEVEL
    if not args.input:
        raise InputError("no INPUT given (or use --demo)")
    if not Path(args.input).exists():
        raise InputError(f"{args.input} does not exist")
    return load_volume(args.input, spacing_zyx_mm=args.spacing, on_progress=on_progress), math.nan
