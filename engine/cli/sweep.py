"""``bonemesh sweep``: its arguments and the command (the sweep itself is the library ``engine.paper.sweep``).

bonemesh sweep INPUT --voxel-size Z,Y,X (--iso V | --preset bone --hu-offset 1024) -o OUTDIR
               [--reductions 0.2,0.3,...] [--iterations 1,5,...] [--repeats 3] [--slices 64] [--points 200000]
               [--crop Z0:Z1,Y0:Y1,X0:X1] [--stride N] [--no-mc33] [--full-runs] [--resume] [--device ...]
bonemesh sweep --demo -o OUTDIR                    (bundled headsq CT at level 1150)
bonemesh sweep --phantom 952,1024,1024 -o OUTDIR   (engine.data.phantom)
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from engine.cli.args import add_input_args, add_level_args, default, output_folder
from engine.errors import InputError
from engine.paper.sweep import SweepConfig
from engine.types import Volume


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(p) for p in text.split(",") if p.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(p) for p in text.split(",") if p.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _crop(text: str) -> tuple[slice, slice, slice]:
    try:
        parts = [p.split(":") for p in text.split(",")]
        slices = tuple(slice(int(a) if a else None, int(b) if b else None) for a, b in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected Z0:Z1,Y0:Y1,X0:X1 voxel ranges, got {text!r}") from None
    if len(slices) != 3:
        raise argparse.ArgumentTypeError(f"expected three ranges Z0:Z1,Y0:Y1,X0:X1, got {text!r}")
    return slices  # type: ignore[return-value]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``bonemesh sweep`` on an ``argparse`` subparsers object (defaults from ``SweepConfig``)."""
    p = subparsers.add_parser("sweep", help="the paper's parameter sweep (Tables 1 and 2) with accuracy metrics")
    add_input_args(p, "output folder")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--demo", action="store_true", help="the bundled headsq CT at level 1150")
    src.add_argument("--phantom", type=_ints, help="bone phantom Z,Y,X (engine.data.phantom)")
    add_level_args(p)
    cfg = {f.name: f.default for f in dataclasses.fields(SweepConfig)}
    p.add_argument("--crop", type=_crop, help="keep voxels Z0:Z1,Y0:Y1,X0:X1 (python ranges, before --stride)")
    p.add_argument("--stride", type=int, default=1, help="keep every Nth sample along each axis (default 1)")
    p.add_argument("--reductions", type=_floats, default=cfg["reductions"], help="default %(default)s")
    p.add_argument("--iterations", type=_ints, default=cfg["iterations"], help="default %(default)s")
    p.add_argument("--repeats", type=int, default=cfg["repeats"], help="timed runs per row (default %(default)s)")
    p.add_argument("--slices", type=int, default=cfg["max_slices"], help="slices compared, 0 = all (%(default)s)")
    p.add_argument("--points", type=int, default=cfg["n_points"], help="surface samples per mesh (default %(default)s)")
    p.add_argument("--seed", type=int, default=cfg["seed"], help="sampling seed (default %(default)s)")
    p.add_argument("--no-mc33", action="store_true", help="skip the scikit-image (Lewiner) MC33 CPU row")
    p.add_argument("--full-runs", action="store_true", help="run the whole pipeline for every pair")
    p.add_argument("--resume", action="store_true", help="keep the rows already in OUTDIR (same input)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def _input(args: argparse.Namespace) -> tuple[Volume, float]:
    from engine.cli.args import load_input
    from engine.level import choose_level
    from engine.params import IsoParams, ReconParams

    iso = args.iso
    if args.phantom:
        from engine.data.phantom import BONE_LEVEL, bone_phantom

        if len(args.phantom) != 3 or min(args.phantom) < 8:
            raise InputError(f"--phantom expects Z,Y,X sizes of at least 8, got {args.phantom}")
        volume = Volume(
            bone_phantom(tuple(args.phantom)),
            args.spacing or (0.05, 0.05, 0.05),
            units="raw",
            source={"generator": "engine.data.phantom.bone_phantom", "shape_zyx": list(args.phantom)},
        )
        iso = BONE_LEVEL if iso is None and args.preset is None else iso
    else:
        volume, demo_iso = load_input(args)
        iso = demo_iso if iso is None and args.preset is None and args.demo else iso
    if args.stride < 1:
        raise InputError(f"--stride must be >= 1, got {args.stride}")
    data = volume.data[args.crop] if args.crop else volume.data
    if args.stride > 1:
        data = data[:: args.stride, :: args.stride, :: args.stride]
    if min(data.shape) < 8:
        raise InputError(f"the cropped volume {data.shape} is too small (at least 8 samples per axis)")
    spacing = tuple(float(s) * args.stride for s in volume.spacing_zyx_mm)
    volume = dataclasses.replace(volume, data=np.ascontiguousarray(data), spacing_zyx_mm=spacing)
    try:
        params = ReconParams(iso=IsoParams(iso=iso, preset=args.preset, hu_offset=args.hu_offset))
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if iso is None and args.preset is None:
        raise InputError("--iso LEVEL or --preset is required: the sweep's ground truth is the voxels >= level")
    return volume, choose_level(volume, params)[0]


def run(args: argparse.Namespace) -> int:
    """``bonemesh sweep``: run the sweep and print where the tables are. Returns the exit code (0)."""
    from engine.paper.sweep import run_sweep
    from engine.paper.sweep_report import scores

    output_folder(args.output)
    try:
        config = SweepConfig(
            reductions=tuple(args.reductions),
            iterations=tuple(args.iterations),
            repeats=args.repeats,
            max_slices=None if args.slices == 0 else args.slices,
            n_points=args.points,
            seed=args.seed,
            mc33_reference=not args.no_mc33,
            full_runs=args.full_runs,
            angle_deg=default(SweepConfig, "angle_deg"),
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None
    volume, level = _input(args)
    meta = {"arguments": {k: v for k, v in vars(args).items() if k not in ("command", "func")}}
    rows = run_sweep(
        volume, level, args.output, config, device=args.device, resume=args.resume, meta=meta,
        log=(lambda s: None) if args.quiet else None,
    )  # fmt: skip
    best = next((s for s in scores(rows) if s["best"]), None)
    print(f"{len(rows)} rows -> {Path(args.output) / 'tables.md'}")  # noqa: T201 - the command's summary
    if best:
        print(f"best: R={best['reduction']:g}, {best['iterations']} it, score {best['score']:.4f}")  # noqa: T201
    return 0
