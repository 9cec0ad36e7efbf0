"""``bonemesh orient OUTPUT_FOLDER --first-slice superior|inferior [--flip-lr] [--flip-ap]``: place a finished
model of an image stack in another orientation and write every output file again, without reconstructing
(``engine.job.reorient``). The options are those of ``bonemesh reconstruct`` and mean the same: the orientation the
stack has, absolute (repeating the command changes nothing); the report records the new frame.

The cranium PNG stack, reconstructed with the defaults, comes out upside down and facing backwards:
``bonemesh orient out/ --first-slice inferior --flip-ap`` turns it over (a half turn about the left-right axis).
"""

from __future__ import annotations

import argparse
from typing import Any

from engine.cli.args import add_orient_args, orient_params


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``bonemesh orient`` on an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "orient",
        help="place a finished model in another stack orientation and write its files again (no reconstruction)",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("folder", metavar="OUTPUT_FOLDER", help="a folder written by 'bonemesh reconstruct'")
    add_orient_args(p)
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default auto)")
    return p


def run(args: argparse.Namespace) -> int:
    """Re-orient the folder; one line on stdout: the new frame and the files written."""
    from engine.job.reorient import reorient
    from engine.orient import describe_stack_convention

    orient = orient_params(args)
    paths = reorient(args.folder, orient, device=args.device)
    print(f"{args.folder}: {describe_stack_convention(orient)}; wrote {', '.join(paths)}")  # noqa: T201
    return 0
