"""``bonemesh reconstruct`` for label maps and pieces (``engine.cli`` calls in here):

    bonemesh reconstruct SEG.nii.gz|SEG.nrrd|SEG.seg.nrrd -o OUT      a model per label (detected by the suffix)
    bonemesh reconstruct FILE --labels -o OUT                          forced: an integer NIfTI/NRRD, a DICOM SEG
                                                                      file (own grid) or a folder of SEG + its CT
    bonemesh reconstruct CT --pieces N -o OUT                          the N largest bone pieces as parts
    ... --roi Z0:Z1,Y0:Y1,X0:X1 [--roi-units voxels|mm]               crop first (mm: x, y, z in the patient frame)
    ... --segments 1,femur                                             only these segments (numbers or names)

Writes ``labels/<name>.stl`` per label (binary, LPS mm, watertight), ``labels.zip`` of them, ``model.glb`` /
``phone.glb`` / ``ar.glb`` with a named, coloured node per label, ``preview.png`` and ``report.json`` (``labels``:
name, value, colour, file, faces, volume, area, watertight per label) into OUT, all or nothing
(``engine.labels.outputs.write_label_outputs``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from engine.errors import InputError
from engine.params import PiecesParams, RoiParams

__all__ = ["add_label_args", "apply_roi", "roi_params", "run_labels", "wants_labels"]


def add_label_args(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("label maps, pieces and a region of interest (docs/labels.md)")
    group.add_argument(
        "--labels", action="store_true", help="INPUT is a label map (integer NIfTI/NRRD, DICOM SEG, SEG+CT folder)"
    )
    group.add_argument("--pieces", type=int, metavar="N", help="keep the N largest bone pieces as separate parts")
    group.add_argument("--roi", metavar="A0:A1,B0:B1,C0:C1", help="crop to this box before anything runs")
    group.add_argument(
        "--roi-units",
        choices=("voxels", "mm"),
        default="voxels",
        help="voxels: z,y,x indices (end exclusive); mm: x,y,z in the patient (LPS) frame",
    )
    group.add_argument("--segments", metavar="S1,S2", help="only these segments (numbers or names, commas between)")


def roi_params(args: argparse.Namespace) -> RoiParams | None:
    """``--roi`` as ``RoiParams`` (None when not given). Raises InputError on a malformed box."""
    if not getattr(args, "roi", None):
        return None
    try:
        ranges = [tuple(float(v) for v in part.split(":")) for part in args.roi.split(",")]
        if len(ranges) != 3 or any(len(r) != 2 for r in ranges):
            raise ValueError(f"--roi takes three LO:HI ranges separated by commas, got {args.roi!r}")
        box = ((ranges[0][0], ranges[0][1]), (ranges[1][0], ranges[1][1]), (ranges[2][0], ranges[2][1]))
        return RoiParams(box, units=args.roi_units)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def apply_roi(args: argparse.Namespace, grid: Any, orient: Any = None) -> Any:
    """The scan or label map cropped to ``--roi`` (as it is without one)."""
    from engine.labels.pieces import crop_roi

    roi = roi_params(args)
    return grid if roi is None else crop_roi(grid, roi, orient)


def wants_labels(args: argparse.Namespace) -> bool:
    """Whether ``reconstruct`` makes a model per label: ``--labels``, ``--pieces`` or a label-map suffix."""
    from engine.io.labelmaps import is_label_path

    if getattr(args, "labels", False) or getattr(args, "pieces", None) is not None:
        return True
    return bool(getattr(args, "input", None)) and is_label_path(args.input)


def _label_volume(args: argparse.Namespace, params: Any) -> Any:
    from engine.cli_args import load_input
    from engine.io.labelmaps import read_labels

    if args.pieces is not None:
        import dataclasses

        from engine.labels.pieces import bone_pieces

        try:
            pieces = PiecesParams(count=args.pieces)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        volume, demo_level = load_input(args)
        if args.demo and args.iso is None and args.preset is None:
            params = dataclasses.replace(params, iso=dataclasses.replace(params.iso, iso=demo_level))
        return bone_pieces(apply_roi(args, volume, params.orient), params, pieces)
    if not args.input or not Path(args.input).exists():
        raise InputError(f"{args.input or 'INPUT'} does not exist")
    if Path(args.input).is_dir():
        from engine.labels.dicom_seg import read_seg_folder

        return apply_roi(args, read_seg_folder(args.input), params.orient)
    return apply_roi(args, read_labels(args.input), params.orient)


def run_labels(args: argparse.Namespace, params: Any, out: Path) -> dict[str, Any]:
    """Read or make the label map, mesh every label and write the files into ``out`` (a temporary folder first,
    moved in when complete). Returns the report."""
    from engine.labels.outputs import write_label_outputs
    from engine.labels.parts import label_models

    lv = _label_volume(args, params)
    if getattr(args, "segments", None):
        from engine.labels.pieces import select_segments

        lv = select_segments(lv, [w.strip() for w in args.segments.split(",") if w.strip()])
    models = label_models(lv, params, device=args.device, orient=params.orient)
    paths = write_label_outputs(models, out, params, device=args.device, extra={"input": _input(lv)}, stl_folder=True)
    report: dict[str, Any] = json.loads(paths["report.json"].read_text())
    return report


def _input(lv: Any) -> dict[str, Any]:
    return {
        "shape_zyx": list(lv.labels.shape),
        "spacing_zyx_mm": list(lv.spacing_zyx_mm),
        "origin_lps_mm": list(lv.origin_mm),
        "segments": len(lv.segments),
    }


def summary(report: dict[str, Any]) -> None:
    """One line per label on stdout."""
    rows = report["labels"]
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        print(  # noqa: T201 - the command's summary
            f"{r['name']:<{width}}  {r['faces']:>8,} faces  {r['volume_mm3']:>12,.1f} mm3  {r['area_mm2']:>10,.1f} mm2"
            f"  watertight {r['watertight']}  {r['file']}"
        )
