"""``run_job``: one job from its input to its files, the same for the worker and every CLI command.

It picks the plan once from the spec and the input's content:

* ``labels``: the input holds a label map (an integer NIfTI, NRRD / .seg.nrrd, a DICOM SEG with or without its CT;
  found by content, ``engine.labels.uploads.find_label_upload``, the same on every path): a model per label;
* ``pieces``: a scan's N largest bone pieces, each its own part;
* ``scan``: the EMC33 pipeline (``engine.job.pipeline.reconstruct``) and its files
  (``engine.job.outputs.write_outputs``),
  the defect and its template included as a stage of it when ``spec.recon.defect`` asks.

A ``roi`` crops the scan or the label map first. Every file goes through the output registry
(``engine.export.files``) into ``outdir``, all or nothing. Progress is reported as ``on_progress(stage, fraction)``
over the whole job: loading up to ``shares[0]``, meshing up to ``shares[1]``, then the files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from engine.errors import InputError
from engine.job.runtime import Runtime
from engine.job.spec import JobSpec
from engine.types import Volume

__all__ = ["JobResult", "run_job"]

OnProgress = Callable[[str, float], None]
SHARES = (0.05, 0.9)  # the job's fraction when loading ends, and when the files begin


@dataclass
class JobResult:
    """What a job made: ``plan`` (``"scan"``, ``"labels"`` or ``"pieces"``), its files by name (in the registry's
    order), the report (as written to report.json), and the scan as it was meshed (``volume``: scan and pieces
    jobs; None for a label map)."""

    plan: str
    paths: dict[str, Path]
    report: dict[str, Any]
    volume: Volume | None = None


def run_job(
    source: str | Path | Volume,
    outdir: str | Path,
    spec: JobSpec,
    runtime: Runtime,
    *,
    on_progress: OnProgress | None = None,
    label: str = "the upload",
    shares: tuple[float, float] = SHARES,
) -> JobResult:
    """Run one job (see the module docstring): ``source`` is a path (a scan, a label map, a zip or folder of
    either) or a loaded ``Volume`` (a scan); ``label`` names it in messages.

    Raises:
        InputError: the input cannot give what the spec asks (NoSpacingError, LabelError, EmptySurfaceError, ...),
            with a message naming ``label``; nothing is written.
        StageError: a stage failed otherwise.
    """
    job = _Job(Path(outdir), spec, runtime, on_progress or _quiet, shares)
    inp = spec.input
    found = None
    if not isinstance(source, Volume) and inp.kind != "scan" and inp.pieces is None:
        from engine.labels.uploads import find_label_upload

        found = find_label_upload(source, label, force=inp.kind == "labels")
    elif isinstance(source, Volume) and inp.kind == "labels":
        raise InputError(f"{label} is a loaded scan, not a label map")
    if found is not None:
        return _label_map(job, source, found, label)
    if inp.segments and inp.pieces is None:
        raise InputError("segments picks among a label map's segments (or a CT's pieces); this upload is a CT scan")
    volume = _load(job, source)
    if inp.pieces is not None:
        return _pieces(job, volume)
    return _scan(job, volume)


@dataclass(frozen=True)
class _Job:
    """What every step of one job reads: where the files go, the spec, the runtime, its progress and shares."""

    outdir: Path
    spec: JobSpec
    runtime: Runtime
    progress: OnProgress
    shares: tuple[float, float]


def _quiet(stage: str, fraction: float) -> None:
    """No progress wanted."""


class _Steps:
    """A stage's own fraction (0..1, e.g. slices decoded) as the job's, passed on only when it moved by a hundredth
    of the job: a worker records each report in its database, and a scan has thousands of slices."""

    def __init__(self, progress: OnProgress, stage: str, share: float) -> None:
        self.progress, self.stage, self.share, self.last = progress, stage, share, -1.0

    def __call__(self, fraction: float) -> None:
        done = self.share * fraction
        if done - self.last >= 0.01 or (fraction >= 1.0 and done > self.last):
            self.last = done
            self.progress(self.stage, done)


def _load(job: _Job, source: str | Path | Volume) -> Volume:
    """The scan, loaded on the runtime's decoders (``engine.io.load_volume``) and cropped to the roi."""
    spec, runtime, progress, end = job.spec, job.runtime, job.progress, job.shares[0]
    if isinstance(source, Volume):
        volume = source
    else:
        from engine.io import codecs, load_volume

        codecs.USE_IMAGECODECS = runtime.png_decoder != "pillow"
        volume = load_volume(
            source,
            spacing_zyx_mm=spec.input.spacing_zyx_mm,
            threads=runtime.decode_threads,
            processes=runtime.decode_processes,
            allocate=runtime.volumes(),  # reused from job to job; page-locked for the upload to a CUDA device
            rows=runtime.rows(),  # on a GPU, PNG slices are only inflated on the host (engine.io.png_rows)
            on_progress=_Steps(progress, "loading", end),
        )
    if spec.input.roi is not None:  # cropped before anything runs
        from engine.labels.pieces import crop_roi

        volume = crop_roi(volume, spec.input.roi, spec.recon.orient)
    progress("loading", end)
    return volume


def _scan(job: _Job, volume: Volume) -> JobResult:
    """The EMC33 pipeline and its files (the defect as one of its stages)."""
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    load_end, mesh_end = job.shares

    def within(stage: str, fraction: float) -> None:
        job.progress(stage, load_end + (mesh_end - load_end) * fraction)

    device, budget, recon = job.runtime.backend, job.runtime.budget, job.spec.recon
    result = reconstruct(volume, recon, device=device, on_progress=within, max_device_bytes=budget)
    job.progress("writing", mesh_end)
    paths = write_outputs(result, job.outdir, recon, device=device, max_device_bytes=budget)
    return JobResult("scan", paths, dict(result.report), volume)


def _label_map(job: _Job, source: Any, found: Any, label: str) -> JobResult:
    """A model per label of a label map (cropped to the roi; only the segments asked for)."""
    from engine.labels.pieces import crop_roi
    from engine.labels.uploads import read_label_upload

    lv = read_label_upload(source, found, label)
    if job.spec.input.roi is not None:
        lv = crop_roi(lv, job.spec.input.roi, job.spec.recon.orient)
    paths, report = _label_models(job, lv)
    return JobResult("labels", paths, report)


def _pieces(job: _Job, volume: Volume) -> JobResult:
    """A scan's largest bone pieces, each its own part."""
    from engine.labels.pieces import bone_pieces

    assert job.spec.input.pieces is not None
    lv = bone_pieces(volume, job.spec.recon, job.spec.input.pieces)
    paths, report = _label_models(job, lv)
    return JobResult("pieces", paths, report, volume)


def _label_models(job: _Job, lv: Any) -> tuple[dict[str, Path], dict[str, Any]]:
    """Mesh every label (``engine.labels.parts.label_models``) and write a label job's files."""
    import json

    from engine.export.files import REPORT_JSON
    from engine.labels.outputs import write_label_outputs
    from engine.labels.parts import label_models
    from engine.labels.pieces import select_segments

    spec, device = job.spec, job.runtime.backend
    if spec.input.segments:
        lv = select_segments(lv, list(spec.input.segments))
    job.progress("labels", job.shares[0])
    models = label_models(lv, spec.recon, device=device, orient=spec.recon.orient)
    job.progress("writing", job.shares[1])
    extra = {"input": _label_input(lv)}
    paths = write_label_outputs(
        models, job.outdir, spec.recon, device=device, extra=extra, stl_folder=spec.outputs.label_stl_folder
    )
    return paths, json.loads(paths[REPORT_JSON].read_text())


def _label_input(lv: Any) -> dict[str, Any]:
    """The report's ``input`` block of a label job."""
    return {
        "shape_zyx": list(lv.labels.shape),
        "spacing_zyx_mm": list(lv.spacing_zyx_mm),
        "origin_lps_mm": list(lv.origin_mm),
        "segments": len(lv.segments),
    }


def with_recon(spec: JobSpec, **changes: Any) -> JobSpec:
    """``spec`` with fields of its ``ReconParams`` replaced (``dataclasses.replace``), checked again."""
    return dataclasses.replace(spec, recon=dataclasses.replace(spec.recon, **changes))
