"""Argument parsing shared by the ``bonemesh`` commands: voxel size, level, orientation, pipeline options.

Every default comes from the parameter dataclasses (``engine.params``), so the CLI, the Python API and the job
parameters cannot drift apart. Only the CLI modules import this one.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from engine.errors import InputError, NoSpacingError
from engine.params import (
    FIRST_SLICE_CHOICES,
    ISO_PRESETS_HU,
    BodyMaskParams,
    DecimateParams,
    IslandParams,
    IsoParams,
    OrientParams,
    PiecesParams,
    PreprocessParams,
    ReconParams,
    SmoothParams,
    decimate_of,
    islands_of,
)
from engine.types import Volume

if TYPE_CHECKING:
    from engine.budget import Budget
    from engine.defect.params import DefectParams
    from engine.io.png_rows import DeviceRows
    from engine.job.spec import JobSpec
    from engine.params import RoiParams

Spacing = tuple[float, float, float]


def default(kind: type, name: str) -> Any:
    """The default of a parameter dataclass's field (for argparse defaults and help texts)."""
    for f in dataclasses.fields(kind):
        if f.name == name:
            return f.default
    raise KeyError(f"{kind.__name__} has no field {name!r}")


def _axes(text: str) -> Spacing:
    """Three positive mm values in z, y, x order, or named (``z=1.5,y=0.9,x=0.9``, any order); returned as
    (z, y, x)."""
    parts = [p.strip() for p in text.split(",")]
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
            vals = nums
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected three numbers Z,Y,X in mm, or named axes z=..,y=..,x=.., got {text!r}"
        ) from None
    if not all(math.isfinite(v) and v > 0 for v in vals):
        raise argparse.ArgumentTypeError(f"expected three positive voxel sizes in mm, got {text!r}")
    return vals


def voxel_size_zyx(text: str) -> Spacing:
    """``--voxel-size Z,Y,X`` (and its older name ``--spacing``): z, y, x in mm, the order of the API's ``spacing``,
    the page's field and the library's ``spacing_zyx_mm``; or named axes in any order (``z=1.5,y=0.9,x=0.9``).

    ``--voxel-size`` was x, y, z before this order was made one everywhere, so three bare numbers shaped like an
    x, y, z size (two equal values first or around the odd one: ``0.957,0.957,1.5``) are refused, not read in the
    new order: an old command would otherwise print a model squashed along the wrong axis. Named axes are taken as
    given (a swapped-looking named size is only warned about)."""
    from engine.params import spacing_order_warning

    spacing = _axes(text)
    warning = None if "=" in text else spacing_order_warning(spacing)
    if warning is not None and warning["likely_zyx_mm"] is not None:
        z, y, x = spacing
        raise argparse.ArgumentTypeError(
            f"{text!r} looks like an x, y, z voxel size (CT pixels are square, so the two equal values are the "
            f"in-plane ones), but --voxel-size is z, y, x: name the axes to say which you mean, e.g. "
            f"{voxel_size_option(warning['likely_zyx_mm'])[13:]} (or z={z:g},y={y:g},x={x:g} to keep it as typed)"
        )
    return spacing


def describe_voxel_size(spacing: Spacing) -> str:
    """The voxel size with its axes named, so that the order cannot be misread."""
    z, y, x = spacing
    return f"z {z:g} mm, y {y:g} mm, x {x:g} mm (z: slice step, y: image rows, x: image columns)"


def voxel_size_option(spacing: Sequence[float]) -> str:
    """``--voxel-size`` for a (z, y, x) voxel size, with its axes named (as a warning suggests it)."""
    z, y, x = spacing
    return f"--voxel-size z={z:g},y={y:g},x={x:g}"


def voxel_size_warning(spacing: Spacing | None) -> str | None:
    """The CLI's sentence when a given voxel size looks swapped (``engine.params.spacing_order_warning``), with the
    option that gives the likely size; None when it does not."""
    from engine.params import spacing_order_warning

    warning = spacing_order_warning(spacing) if spacing is not None else None
    if warning is None:
        return None
    likely = warning["likely_zyx_mm"]
    fix = f"; if so, give {voxel_size_option(likely)}" if likely else ""
    return f"{warning['message']}{fix} (--voxel-size is z, y, x; name the axes to be sure)"


def add_input_args(parser: argparse.ArgumentParser, what: str) -> None:
    """INPUT, ``-o``, the voxel size (z, y, x, or named axes) and the device."""
    parser.add_argument(
        "input", nargs="?",
        help="slice archive or folder, DICOM series (zip or folder), TIFF or BigTIFF, .npy, or OME-Zarr (a folder, a "
        "zip of one, or s3://bucket/key; one level: scan.ome.zarr/LEVEL)",
    )  # fmt: skip
    parser.add_argument("-o", "--output", required=True, help=what)
    size = parser.add_mutually_exclusive_group()
    size.add_argument(
        "--voxel-size", dest="spacing", type=voxel_size_zyx, metavar="Z,Y,X",
        help="voxel size in mm in z, y, x order (z: slice step, y: row spacing, x: column spacing; the order of the "
        "API and the page), or named in any order: z=1.5,y=0.5,x=0.5. Image stacks need it; DICOM carries it",
    )  # fmt: skip
    size.add_argument("--spacing", dest="spacing", type=voxel_size_zyx, metavar="Z,Y,X", help="same as --voxel-size")
    parser.add_argument(
        "--zarr-level", default=None, metavar="LEVEL",
        help="an OME-Zarr's resolution level: its index (0, the default: full resolution) or its path (the same as "
        "INPUT/LEVEL; the API's zarr_level)",
    )  # fmt: skip
    parser.add_argument(
        "--device", default="auto",
        help="auto, cpu, cuda[:N] or opencl[:N] (default auto); reconstruct: several GPUs for one scan, a list such as "
        "cuda:0,cuda:1, or cuda:all (the volume is split in z over them: docs/multi-gpu.md)",
    )  # fmt: skip
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


def add_host_arg(parser: argparse.ArgumentParser) -> None:
    """``--max-host-bytes``: the host memory bound of a job (``engine.budget.Budget.host_bytes``)."""
    parser.add_argument(
        "--max-host-bytes", default=None, metavar="SIZE", type=_host_bound,
        help="host memory bound, e.g. 16GiB: a scan larger than half of it is read from disk slab by slab, never "
        "whole (TIFF folder, multi-page TIFF/BigTIFF, OME-Zarr, .npy); on the CPU the device budget comes out of it; "
        "default none (docs/host-memory.md)",
    )  # fmt: skip


def _host_bound(text: str) -> int | None:
    """``--max-host-bytes``: a byte count (``engine.budget.parse_bytes``)."""
    from engine.budget import parse_bytes

    try:
        return parse_bytes(text)
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
        preprocess = None
        if args.threshold is not None or args.canny_sigma is not None or args.area_opening_px is not None:
            preprocess = PreprocessParams(
                threshold=args.threshold, canny_sigma=args.canny_sigma, area_opening_px=args.area_opening_px
            )
        return ReconParams(
            preprocess=preprocess,
            iso=IsoParams(iso=args.iso, preset=args.preset, hu_offset=args.hu_offset, closed=not args.open),
            islands=islands_of(args.min_island_mm3, args.keep_largest, keep_specks=args.keep_specks),
            decimate=decimate_of(args.reduction, args.max_triangles),
            smooth=SmoothParams(iterations=args.iterations, angle_deg=args.angle),
            orient=orient_params(args),
            body=None if args.keep_outside_body else BodyMaskParams(outline_hu=args.outline_hu),
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None


def job_spec(args: argparse.Namespace) -> JobSpec:
    """The ``JobSpec`` of ``reconstruct``'s arguments (``engine.job``: the same object the API makes of a request):
    the pipeline's options, what the input is (``--labels``, ``--pieces``, ``--roi``, ``--segments``, the voxel
    size) and the CLI's layout of a label job's files; ``--demo``: the bundled scan's orientation, voxel size and
    bone level (unless a level is given).

    Raises:
        InputError: an invalid value or combination (exit code 2).
    """
    from engine.job.spec import InputSpec, JobSpec, OutputSpec

    recon = recon_params(args)
    if getattr(args, "defect", False):
        recon = dataclasses.replace(recon, defect=defect_params(args))
    spacing = args.spacing
    if getattr(args, "demo", False):
        from engine.data import HEADSQ_FIRST_SLICE, HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM

        recon = dataclasses.replace(recon, orient=OrientParams(first_slice=HEADSQ_FIRST_SLICE))
        if args.iso is None and args.preset is None:
            recon = dataclasses.replace(recon, iso=dataclasses.replace(recon.iso, iso=HEADSQ_LEVEL))
        spacing = spacing or HEADSQ_SPACING_ZYX_MM
    try:
        inp = InputSpec(
            kind="labels" if getattr(args, "labels", False) else "auto",
            spacing_zyx_mm=spacing,
            roi=roi_params(args),
            pieces=None if getattr(args, "pieces", None) is None else PiecesParams(count=args.pieces),
            segments=segments_of(args),
            zarr_level=getattr(args, "zarr_level", None),
        )
        return JobSpec(recon=recon, input=inp, outputs=OutputSpec(label_stl_folder=True))
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

    rows = _png_rows(getattr(args, "device", None))
    if getattr(args, "demo", False):
        from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

        spacing = args.spacing or HEADSQ_SPACING_ZYX_MM
        return load_volume(HEADSQ_ZIP, spacing_zyx_mm=spacing, on_progress=on_progress, rows=rows), HEADSQ_LEVEL
    if not args.input:
        raise InputError("no INPUT given (or use --demo)")
    from engine.io.omezarr import is_remote

    if not is_remote(args.input) and not Path(args.input).exists():
        raise InputError(f"{args.input} does not exist")
    try:
        level = getattr(args, "zarr_level", None)
        volume = load_volume(args.input, spacing_zyx_mm=args.spacing, on_progress=on_progress, rows=rows, level=level)
        return volume, math.nan
    except NoSpacingError as exc:  # the library names spacing_zyx_mm: say it with the command's option
        raise InputError(no_voxel_size_message(args.input, exc)) from None


def _png_rows(device: str | None) -> DeviceRows | None:
    """PNG slices' rows unfiltered on the command's ``--device`` where it is a GPU (``engine.io.png_rows``); None on
    the CPU, or where the spec is not usable (the stage that runs on it reports that)."""
    from engine.io.png_rows import device_rows

    try:
        return None if device is None else device_rows(device)
    except ValueError:
        return None


def no_voxel_size_message(path: str, exc: NoSpacingError) -> str:
    """The CLI's words for an input without a voxel size: its name, what it lacks and the option that gives it."""
    name = Path(path).name or path
    pixel = getattr(exc, "pixel_yx_mm", None)
    if pixel is not None:
        y, x = pixel
        return (
            f"{name}: the TIFF tags give the pixel size (y {y:g} mm, x {x:g} mm) but not the slice spacing; give "
            f"--voxel-size z=SLICE_STEP,y={y:g},x={x:g} (mm)"
        )
    return (
        f"{name}: the images do not say how large a voxel is; give --voxel-size Z,Y,X in mm (z: slice step, "
        "y: row spacing, x: column spacing), e.g. --voxel-size z=1.5,y=0.5,x=0.5"
    )


def add_label_args(parser: argparse.ArgumentParser) -> None:
    """``reconstruct``'s label maps, pieces and region of interest (docs/labels.md): a label map is found by its
    content without ``--labels`` too."""
    group = parser.add_argument_group("label maps, pieces and a region of interest (docs/labels.md)")
    group.add_argument(
        "--labels", action="store_true", help="INPUT is a label map (integer NIfTI/NRRD, DICOM SEG, SEG+CT folder)"
    )
    group.add_argument("--pieces", type=int, metavar="N", help="keep the N largest bone pieces as separate parts")
    group.add_argument(
        "--roi",
        metavar="LO:HI,LO:HI,LO:HI",
        help="crop to this box before anything runs: voxel indices in z,y,x order (end exclusive), e.g. "
        "0:60,0:256,0:128; with --roi-units mm, mm in x,y,z order (patient LPS frame), e.g. 0:120,-50:250,-10:160 "
        "(a box starting below 0: --roi=-10:...)",
    )
    group.add_argument(
        "--roi-units",
        choices=("voxels", "mm"),
        default="voxels",
        help="the units and order of --roi: voxels (default): z,y,x indices; mm: x,y,z in the patient (LPS) frame",
    )
    group.add_argument("--segments", metavar="S1,S2", help="only these segments (numbers or names, commas between)")


def roi_params(args: argparse.Namespace) -> RoiParams | None:
    """``--roi`` as ``RoiParams`` (None when not given). Raises InputError on a malformed box."""
    from engine.params import RoiParams

    if not getattr(args, "roi", None):
        return None
    try:
        ranges = [tuple(float(v) for v in part.split(":")) for part in args.roi.split(",")]
        if len(ranges) != 3 or any(len(r) != 2 for r in ranges):
            order = "x,y,z in mm" if args.roi_units == "mm" else "z,y,x voxel indices"
            raise ValueError(f"--roi takes three LO:HI ranges separated by commas ({order}), got {args.roi!r}")
        box = ((ranges[0][0], ranges[0][1]), (ranges[1][0], ranges[1][1]), (ranges[2][0], ranges[2][1]))
        return RoiParams(box, units=args.roi_units)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def segments_of(args: argparse.Namespace) -> tuple[int | str, ...] | None:
    """``--segments``: numbers or names, commas between (None when not given)."""
    text = getattr(args, "segments", None)
    if not text:
        return None
    return tuple(w.strip() for w in text.split(",") if w.strip())  # a number or a name: select_segments reads both


def _point(text: str) -> tuple[float, float, float]:
    """``--hint-point L,P,S``: three finite numbers, mm in the patient frame (LPS: model.stl's x, y, z)."""
    try:
        vals = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm (patient frame, LPS), got {text!r}") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected three finite numbers X,Y,Z in mm, got {text!r}")
    return vals[0], vals[1], vals[2]


def add_defect_args(parser: argparse.ArgumentParser, *, command: bool) -> None:
    """The defect's hints and limits (defaults from ``DefectParams``): for ``bonemesh defect`` (``command``) as
    ``--min-volume`` / ``--max-faces``; for ``reconstruct``, ``--defect`` turns the step on and the limits are
    ``--defect-min-volume`` / ``--defect-max-faces`` (beside the model's own ``--max-triangles``)."""
    from engine.defect.params import DEFAULT_MAX_FACES, SIDES

    group = parser.add_argument_group("the defect and its mirrored fill template (docs/defect.md)")
    if not command:
        group.add_argument(
            "--defect", action="store_true",
            help="also find the bone's one-sided defect: implant.stl, defect.json, a template node in the GLB files",
        )  # fmt: skip
    group.add_argument("--hint-side", choices=SIDES, help="the defect is on the patient's left or right")
    group.add_argument("--hint-point", type=_point, metavar="L,P,S",
                       help="a point in or next to the defect, mm in the patient frame (LPS): toward the patient's "
                       "left, posterior, superior, as model.stl's x, y, z")  # fmt: skip
    prefix = "--" if command else "--defect-"
    group.add_argument(f"{prefix}min-volume", dest="defect_min_volume", type=float, metavar="MM3",
                       help="smallest defect reported (default: the rule)")  # fmt: skip
    group.add_argument(f"{prefix}max-faces", dest="defect_max_faces", type=int, default=DEFAULT_MAX_FACES,
                       help="decimate the implant to at most this many triangles (default %(default)s)")  # fmt: skip


def defect_params(args: argparse.Namespace) -> DefectParams:
    """The ``DefectParams`` of the defect's arguments.

    Raises:
        InputError: a value ``DefectParams`` refuses (exit code 2).
    """
    from engine.defect.params import DefectParams

    try:
        return DefectParams(
            side=args.hint_side,
            point_lps_mm=args.hint_point,
            min_volume_mm3=args.defect_min_volume,
            max_faces=args.defect_max_faces,
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None
