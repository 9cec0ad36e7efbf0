"""``bonemesh orient OUTPUT_FOLDER (--first-slice superior|inferior [--flip-lr] [--flip-ap] | --reset)``: place a
finished model of an image stack in another orientation and write every output file again, without
reconstructing (``engine.job.reorient``). The options are those of ``bonemesh reconstruct`` and mean the same: the
orientation the stack has, absolute (an option left out takes its default: first slice superior, no flip), never
a change relative to the current one, so repeating the command changes nothing; the report records the new frame.

Without any of them the command refuses to run (exit 2, the current orientation named): it never re-publishes the
default orientation by accident, undoing an earlier ``orient``. ``--reset`` asks for the default orientation
(first slice superior, no flips) and says so. An orientation the folder already has writes nothing.

The cranium PNG stack, reconstructed with the defaults, comes out upside down and facing backwards:
``bonemesh orient out/ --first-slice inferior --flip-ap`` turns it over (a half turn about the left-right axis).
"""

from __future__ import annotations

import argparse
from typing import Any

from engine.cli.args import add_orient_args
from engine.errors import InputError
from engine.params import OrientParams

CHANGE_OPTIONS = "--first-slice superior|inferior, --flip-lr, --flip-ap"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``bonemesh orient`` on an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "orient",
        help="place a finished model in another stack orientation and write its files again (no reconstruction)",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("folder", metavar="OUTPUT_FOLDER", help="a folder written by 'bonemesh reconstruct'")
    add_orient_args(p)
    for action in p._actions:  # left out: not given (the refusal tells "no change asked" from "superior")
        if action.dest == "first_slice":
            action.default = None
            action.help = "image stacks: which end of the patient the first slice is (left out: superior)"
    p.add_argument(
        "--reset", action="store_true",
        help="place the model in the default orientation again: first slice superior, no flips",
    )  # fmt: skip
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default auto)")
    return p


def wanted_orient(args: argparse.Namespace, now: OrientParams) -> OrientParams:
    """The orientation asked for: the options (absolute), or the default with ``--reset``.

    Raises:
        InputError: no option and no ``--reset`` (nothing to change), or ``--reset`` with an option.
    """
    given = args.first_slice is not None or args.flip_lr or args.flip_ap
    if args.reset and given:
        raise InputError(f"--reset places the default orientation; give it alone, or {CHANGE_OPTIONS} without it")
    if not args.reset and not given:
        raise InputError(
            f"{args.folder}: nothing to change; now {_words(now)}. Give the orientation the stack has "
            f"({CHANGE_OPTIONS}: absolute, not relative to the current one) or --reset for the default"
        )
    if args.reset:
        return OrientParams()
    return OrientParams(first_slice=args.first_slice or "superior", flip_lr=args.flip_lr, flip_ap=args.flip_ap)


def _words(orient: OrientParams) -> str:
    return (
        f"first slice {orient.first_slice}, image left = patient's {'left' if orient.flip_lr else 'right'}, "
        f"image top = {'posterior' if orient.flip_ap else 'anterior'}"
    )


def run(args: argparse.Namespace) -> int:
    """Re-orient the folder; one line on stdout: what was, what is now and the files written (or that nothing
    was, the folder being placed so already)."""
    from engine.job.reorient import current_orient, read_report, reorient

    report = read_report(args.folder)
    frame = report.get("frame")
    placed_by = str(frame.get("placed_by", "")) if frame else ""
    params = report.get("parameters") or {}
    if report.get("labels") is not None or placed_by.startswith("DICOM") or params.get("defect") is not None:
        reorient(args.folder, OrientParams(), device=args.device)  # refuses, saying why (a DICOM series, ...)
    now = current_orient(report)
    orient = wanted_orient(args, now)
    what = "reset to the default orientation" if args.reset else "placed"
    if orient == now:
        print(f"{args.folder}: already {_words(now)}; nothing written")  # noqa: T201
        return 0
    paths = reorient(args.folder, orient, device=args.device)
    print(f"{args.folder}: {what}: {_words(orient)} (was {_words(now)}); wrote {', '.join(paths)}")  # noqa: T201
    return 0
