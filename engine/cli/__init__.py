"""The ``bonemesh`` command line (the engine's commands; ``service.cli`` adds ``serve`` and ``worker``).

    bonemesh reconstruct INPUT -o OUTDIR [--voxel-size Z,Y,X] [--iso V | --preset bone ...]
                         [--first-slice superior|inferior] [--flip-lr] [--flip-ap] [--reduction R] ...
    bonemesh reconstruct --demo -o OUTDIR
    bonemesh reconstruct INPUT -o OUTDIR --defect [--hint-side left|right] [--hint-point L,P,S]   (implant.stl too)
    bonemesh isosurface INPUT -o OUT.stl --iso LEVEL [--voxel-size Z,Y,X] [--device ...] [--open]
    bonemesh isosurface --demo -o OUT.stl
    bonemesh sweep ...   (engine.cli.sweep)
    bonemesh orient OUTDIR (--first-slice superior|inferior [--flip-lr] [--flip-ap] | --reset)   (engine.cli.orient)

INPUT is anything ``engine.io.load_volume`` reads: a DICOM series (zip or folder), an archive or folder of
slice images, a multi-page TIFF or a ``.npy`` (z, y, x) volume. ``--voxel-size`` is z, y, x in mm (the API's
and the page's order; ``--spacing`` is the same option) or named axes (``z=1.5,y=0.5,x=0.5``); a size that looks
swapped is warned about. Arguments are parsed in ``engine.cli.args`` (their defaults come from ``engine.params``).

Exit codes: 0 done, 2 bad input or arguments (the reason in one line on stderr, argument errors with a pointer to
``--help``; no output), 1 internal error, 130 interrupted (Ctrl-C: one line, no output folder left behind). The
progress bar is drawn only when stderr is a terminal; otherwise a few progress lines are written.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import time
import typing
from collections.abc import Iterator
from pathlib import Path

from engine.cli.args import (
    add_defect_args,
    add_host_arg,
    add_input_args,
    add_label_args,
    add_orient_args,
    add_recon_args,
    describe_voxel_size,
    job_spec,
    load_input,
    no_voxel_size_message,
    orient_params,
    output_file,
    output_folder,
    voxel_size_option,
    voxel_size_warning,
)
from engine.errors import InputError, NoSpacingError
from engine.report import Report
from engine.types import Volume

LOAD_SHARE = 0.1  # the bar's share for loading the input (the pipeline weights its own stages)
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a command stopped by Ctrl-C


class _Parser(argparse.ArgumentParser):
    """argparse, with an argument error in two lines (the error, and where the usage is) instead of the usage
    block; the subcommands' parsers are of this class too."""

    argv: typing.Sequence[str] = ()

    def parse_known_args(self, args: typing.Any = None, namespace: typing.Any = None) -> typing.Any:
        self.argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> typing.NoReturn:
        prog = self.prog
        commands = next((a.choices for a in self._actions if isinstance(a, argparse._SubParsersAction)), None)
        command = next((arg for arg in self.argv if commands and arg in commands), None)
        if command is not None:  # unrecognised arguments of a subcommand come to the top parser: name its help
            prog = f"{prog} {command}"
        sys.stderr.write(f"{self.prog}: error: {message}\ntry '{prog} --help'\n")
        sys.exit(2)


def build_parser() -> argparse.ArgumentParser:
    """The ``bonemesh`` parser with the engine's subcommands."""
    from engine.cli.orient import add_parser as add_orient_parser
    from engine.cli.sweep import add_parser as add_sweep_parser

    parser = _Parser(prog="bonemesh", description="Bone surface models from CT slice stacks.")
    sub = parser.add_subparsers(dest="command", required=True)
    iso = sub.add_parser("isosurface", help="extract a Marching Cubes 33 surface and write a binary STL (mm)")
    add_input_args(iso, "output .stl path")
    iso.add_argument("--iso", type=float, help="iso level in the volume's units")
    add_orient_args(iso)
    iso.add_argument("--open", action="store_true", help="do not close the surface at the volume's borders")
    iso.add_argument("--demo", action="store_true", help="use the bundled VTK headsq CT head at its bone level")

    rec = sub.add_parser("reconstruct", help="the EMC33 pipeline: model.stl, model.glb, phone.glb, ar.glb, report")
    add_input_args(rec, "output folder")
    add_host_arg(rec)
    add_recon_args(rec)
    add_label_args(rec)  # --labels, --pieces N, --roi, --segments
    add_defect_args(rec, command=False)  # --defect and its hints: the defect as a stage of the job
    rec.add_argument("--demo", action="store_true", help="use the bundled VTK headsq CT head")
    rec.add_argument("--quiet", action="store_true", help="no progress bar")
    add_sweep_parser(sub)
    add_orient_parser(sub)
    from engine.cli.defect import add_parser as add_defect_parser

    add_defect_parser(sub)
    return parser


class _Bar:
    """The run's progress on stderr: one bar redrawn in place when stderr is a terminal; else (a log, a pipe) a
    line at the start and at each quarter, at most five. Errors printed after it start on a new line."""

    open_line = False  # a bar line is on stderr without its newline
    LINES_AT = (0.0, 0.25, 0.5, 0.75, 1.0)  # where a log gets a line

    def __init__(self, quiet: bool, tty: bool | None = None) -> None:
        self.quiet = quiet
        self.tty = sys.stderr.isatty() if tty is None else tty
        self.t0 = time.perf_counter()
        self.last: tuple[str, int] | None = None
        self.lines = 0  # LINES_AT passed (not a terminal)

    def __call__(self, stage: str, fraction: float) -> None:
        if self.quiet:
            return
        if not self.tty:
            self._line(stage, fraction)
            return
        key = (stage, round(fraction * 1000))
        if key == self.last:
            return
        self.last = key
        width = 30
        filled = round(fraction * width)
        sys.stderr.write(
            f"\r[{'#' * filled}{'.' * (width - filled)}] {fraction * 100:5.1f}%  {stage:<12s}"
            f" {time.perf_counter() - self.t0:7.2f} s"
        )
        _Bar.open_line = fraction < 1.0
        if not _Bar.open_line:
            sys.stderr.write("\n")
        sys.stderr.flush()

    def _line(self, stage: str, fraction: float) -> None:
        passed = sum(1 for at in self.LINES_AT if fraction >= at)
        if passed <= self.lines:
            return
        self.lines = passed
        sys.stderr.write(f"bonemesh: {fraction * 100:5.1f}%  {stage} ({time.perf_counter() - self.t0:.1f} s)\n")
        sys.stderr.flush()

    @classmethod
    def end_line(cls) -> None:
        """End an unfinished bar line, so that what follows starts on its own line."""
        if cls.open_line:
            sys.stderr.write("\n")
            sys.stderr.flush()
            cls.open_line = False


def _isosurface(args: argparse.Namespace) -> int:
    from engine.export.stl import to_stl
    from engine.isosurface import marching_cubes_33
    from engine.orient import patient_frame, to_patient
    from engine.types import Mesh

    out = output_file(args.output, ".stl")
    _warn_voxel_size(args)
    volume, _ = load_input(args)
    level = args.iso
    if args.demo and level is None:
        from engine.data import HEADSQ_BONE_LEVEL

        level = HEADSQ_BONE_LEVEL
    if level is None:
        raise InputError("--iso LEVEL is required (the iso value in the volume's units)")
    start = time.perf_counter()
    try:
        verts, faces = marching_cubes_33(
            volume.data, level, spacing=volume.spacing_zyx_mm, device=args.device, closed=not args.open
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None
    seconds = time.perf_counter() - start
    if len(faces) == 0:
        raise InputError(f"no surface at level {level}: the volume's values do not cross it")
    placed = to_patient(Mesh(verts, faces), patient_frame(volume, orient_params(args)))  # LPS mm, as model.stl
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(to_stl(placed.vertices, placed.faces, header="bonemesh isosurface, patient LPS frame, mm"))
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    print(  # noqa: T201 - the command's report
        f"{out}: {len(verts):,} vertices, {len(faces):,} triangles from a {volume.data.shape} volume "
        f"at level {level} in {seconds:.2f} s"
    )
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    """``reconstruct``: the job's spec and runtime from the flags (resolved here, once), then ``engine.job.run_job``
    (the worker's path too): a scan's model, a model per label of a label map (found by content), or a CT's pieces."""
    from engine.io.omezarr import is_remote
    from engine.job import resolve_runtime, run_job

    spec = job_spec(args)
    try:
        # a missing device: exit 2 before loading
        runtime = resolve_runtime(args.device, args.max_device_bytes, max_host_bytes=args.max_host_bytes)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    out = output_folder(args.output)
    _warn_voxel_size(args)
    if args.demo:
        from engine.data import HEADSQ_ZIP

        source: str | Path = HEADSQ_ZIP
    elif not args.input:
        raise InputError("no INPUT given (or use --demo)")
    elif not is_remote(args.input) and not Path(args.input).exists():
        raise InputError(f"{args.input} does not exist")
    else:
        source = args.input  # a path, or an OME-Zarr's s3:// URL (engine.io.omezarr)
    bar = _Bar(args.quiet)
    with _removed_unless_finished(out):
        try:
            result = run_job(
                source, out, spec, runtime, on_progress=bar, label=Path(source).name, shares=(LOAD_SHARE, 1.0)
            )
        except NoSpacingError as exc:  # the library names spacing_zyx_mm: say it with the command's option
            raise InputError(no_voxel_size_message(str(source), exc)) from None
    if result.plan == "scan":
        assert result.volume is not None
        _summary(result.volume, result.report, result.paths)  # type: ignore[arg-type]
    else:
        _label_summary(result.report)
    return 0


def _label_summary(report: dict[str, typing.Any]) -> None:
    """One line per label on stdout; the report's warnings (fewer pieces than asked, say) on stderr."""
    rows = report["labels"]
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        print(  # noqa: T201 - the command's summary
            f"{r['name']:<{width}}  {r['faces']:>8,} faces  {r['volume_mm3']:>12,.1f} mm3  {r['area_mm2']:>10,.1f} mm2"
            f"  watertight {r['watertight']}  {r['file']}"
        )
    for warning in report.get("warnings", []):
        print(f"bonemesh: warning: {warning['message']}", file=sys.stderr)  # noqa: T201


def _warn_voxel_size(args: argparse.Namespace) -> None:
    """Say on stderr, before the run, that a given voxel size looks swapped (the summary and the report say it
    again)."""
    message = None if getattr(args, "demo", False) else voxel_size_warning(args.spacing)
    if message:
        print(f"bonemesh: warning: {message}", file=sys.stderr)  # noqa: T201


@contextlib.contextmanager
def _removed_unless_finished(out: Path) -> Iterator[None]:
    """An output folder that this run creates is removed again when the run does not finish (an error, Ctrl-C):
    no empty or partial folder is left. A folder that existed before is left as it was (``write_outputs`` moves
    its files in only when all are written)."""
    created = not out.exists()
    try:
        yield
    except BaseException:
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise


def _summary(vol: Volume, rep: Report, paths: dict[str, Path]) -> None:
    frame = rep["frame"]
    rows = [
        ("input", f"{tuple(vol.data.shape)} (z, y, x) {vol.data.dtype}, {vol.units}"),
        ("voxel size", describe_voxel_size(vol.spacing_zyx_mm)),
        ("iso level", f"{rep['iso_level']['value']:g} {rep['iso_level']['units']} ({rep['iso_level']['chosen_by']})"),
        ("placed by", frame["placed_by"]),
        ("STL frame", frame["stl"]),
        ("glTF frame", f"{frame['gltf']} (centre {', '.join(f'{c:g}' for c in frame['gltf_centre_lps_mm'])} mm LPS)"),
        ("device", rep["device"]["name"]),
    ]
    body = rep.get("body_mask")
    if body and body.get("applied"):
        rows.append(
            (
                "outside body",
                f"{body['pieces_removed']} piece(s), {_number(body['volume_removed_mm3'])} mm3 removed (couch, "
                "holders)",
            )
        )
    elif body:
        rows.append(("body mask", f"not applied: {body['reason']}"))
    isl = rep.get("islands")
    if isl:
        rows.append(("specks", f"{isl['removed_pieces']} piece(s), {_number(isl['removed_volume_mm3'])} mm3 removed"))
    for stage, secs in rep["stage_seconds"].items():
        counts = rep["counts"].get(stage)
        extra = f"  {counts['faces']:,} faces" if isinstance(counts, dict) and "faces" in counts else ""
        rows.append((stage, f"{secs:8.3f} s{extra}"))
    mesh = rep["mesh"]
    rows.append(
        (
            "model",
            f"{mesh['n_faces']:,} faces, {mesh['components']} piece(s), watertight {mesh['watertight']}, volume "
            f"{_volume(mesh['volume_mm3'])}, area {_number(mesh['area_mm2'])} mm2",
        )
    )
    defect = rep.get("defect")
    if defect:
        rows.append(("defect", _defect_text(defect)))
    for warning in rep.get("warnings", []):
        rows.append(("WARNING", _warning_text(warning)))
    for name, path in paths.items():
        rows.append((name, f"{path.stat().st_size:,} bytes"))
    width = max(len(r[0]) for r in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")  # noqa: T201 - the command's summary table


def _defect_text(defect: dict[str, typing.Any]) -> str:
    """The defect step's answer in one line: where and how large, or why there is no template."""
    if not defect.get("found"):
        return f"none: {defect.get('message', defect.get('code', 'not found'))}"
    rim = defect.get("rim") or {}
    return (
        f"{defect['side']} side, {_number(defect['volume_mm3'])} mm3, slices {defect['slices'][0]}-"
        f"{defect['slices'][1]}, rim gap {rim.get('gap_mm', float('nan')):.2f} mm, implant {defect['implant_faces']:,}"
        " triangles (implant.stl, defect.json)"
    )


def _number(value: float) -> str:
    """A measure with the digits it needs: thousands grouped and whole from 1,000 on, one decimal from 1, three
    significant digits below (a micro-CT model of 0.0302 mm3 is not "0")."""
    if value == 0:
        return "0"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    if abs(value) >= 1:
        return f"{value:.1f}"
    return f"{value:.3g}"


def _volume(mm3: float) -> str:
    """A model's volume in mm3, with millilitres beside from a millilitre on."""
    return f"{_number(mm3)} mm3" + (f" ({mm3 / 1000:,.1f} mL)" if abs(mm3) >= 1000 else "")


def _warning_text(warning: dict[str, typing.Any]) -> str:
    """A report warning for the summary; a voxel size that looks swapped with the option that gives the likely
    one."""
    text = str(warning.get("message", warning))
    likely = warning.get("likely_zyx_mm")
    if warning.get("code") == "voxel_size_order" and likely:
        text += f"; if so, give {voxel_size_option(likely)}"
    return text


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns the exit code (0 done, 2 bad input or arguments, 1 internal error, 130 interrupted)."""
    try:
        args = build_parser().parse_args(argv)
        if args.command == "isosurface":
            return _isosurface(args)
        if args.command == "reconstruct":
            return _reconstruct(args)
        if args.command == "sweep":
            from engine.cli.sweep import run as run_sweep

            return run_sweep(args)
        if args.command == "orient":
            from engine.cli.orient import run as run_orient

            return run_orient(args)
        if args.command == "defect":
            from engine.cli.defect import run as run_defect

            return run_defect(args)
    except InputError as exc:
        _Bar.end_line()
        print(f"bonemesh: error: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    except Exception as exc:
        _Bar.end_line()
        if os.environ.get("BONEMESH_DEBUG") == "1":
            raise
        print(f"bonemesh: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)  # noqa: T201
        return 1
    except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback; the output folder is gone (_reconstruct)
        _Bar.end_line()
        print("bonemesh: interrupted", file=sys.stderr)  # noqa: T201
        return EXIT_INTERRUPTED
    return 1
