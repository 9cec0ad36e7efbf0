"""``run_job``: one job from its input to its files, the same for the worker and every CLI command.

It picks the plan once from the spec and the input's content:

* ``labels``: the input holds a label map (an integer NIfTI, NRRD / .seg.nrrd, a DICOM SEG with or without its CT;
  found by content, ``engine.labels.uploads.find_label_upload``, the same on every path): a model per label;
* ``pieces``: a scan's N largest bone pieces, each its own part, meshed from the scan's own values through the
  model's stages (its surface is the model's there); specks below the island size are not pieces, and are counted;
* ``scan``: the EMC33 pipeline (``engine.job.pipeline.reconstruct``) and its files
  (``engine.job.outputs.write_outputs``),
  the defect and its template included as a stage of it when ``spec.recon.defect`` asks.

A ``roi`` crops the scan or the label map first (a scan after its body outline is found on the whole:
``engine.job.plans.prepare_whole``). Every file goes through the output registry
(``engine.export.files``) into ``outdir``, all or nothing. Progress is reported as ``on_progress(stage, fraction)``
over the whole job: loading up to ``shares[0]``, meshing up to ``shares[1]``, then the files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

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
    predecoded: bool = False,
) -> JobResult:
    """Run one job (see the module docstring): ``source`` is a path (a scan, a label map, a zip or folder of
    either) or a loaded ``Volume`` (a scan); ``label`` names it in messages. ``predecoded``: a scan's slices are
    read from the volume decoded while it was uploaded, where its sidecar is there and still its own
    (``engine.io.predecode``; the same volume, ``input.source.decoded_during_upload`` in the report).

    Raises:
        InputError: the input cannot give what the spec asks (NoSpacingError, LabelError, EmptySurfaceError, ...),
            with a message naming ``label``; nothing is written.
        StageError: a stage failed otherwise.
    """
    progress = on_progress or _quiet
    if runtime.budget.host_bytes is not None:  # freed arrays leave the resident set (engine.heap)
        from engine import heap

        heap.bound_heap()
        progress = _giving_back(progress)
    job = _Job(Path(outdir), spec, runtime, progress, shares, predecoded)
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
    try:
        if inp.pieces is not None:
            return _pieces(job, volume)
        return _scan(job, volume)
    finally:
        _close(source, volume)


@dataclass(frozen=True)
class _Job:
    """What every step of one job reads: where the files go, the spec, the runtime, its progress and shares."""

    outdir: Path
    spec: JobSpec
    runtime: Runtime
    progress: OnProgress
    shares: tuple[float, float]
    predecoded: bool = False


def _quiet(stage: str, fraction: float) -> None:
    """No progress wanted."""


def _giving_back(progress: OnProgress) -> OnProgress:
    """``progress``, and at each new stage the heap's free memory given back (``engine.heap.give_back``)."""
    from engine.heap import give_back

    last = [""]

    def report(stage: str, fraction: float) -> None:
        if stage != last[0]:
            last[0] = stage
            give_back()
        progress(stage, fraction)

    return report


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
    whole = runtime.budget.whole_volume_bytes  # under a host memory bound: a larger scan is read slab by slab
    sliced = pre = None
    level = spec.input.zarr_level  # an OME-Zarr's level (refused by the loaders for any other input)
    if job.predecoded and level is None and not isinstance(source, Volume):  # decoded while it was uploaded
        from engine.io.predecode import load_predecoded

        pre = load_predecoded(
            source,
            spacing_zyx_mm=spec.input.spacing_zyx_mm,
            allocate=runtime.volumes(),
            threads=runtime.decode_threads,
            whole_bytes=whole,
            rows=runtime.rows(),  # a sidecar of PNG rows is unfiltered on the job's GPU
        )
        if pre is not None and not isinstance(pre.data, np.ndarray):
            sliced = pre
    if pre is None and whole is not None and not isinstance(source, Volume):
        from engine.io.slabs import open_slabs

        sliced = open_slabs(
            source, whole, spacing_zyx_mm=spec.input.spacing_zyx_mm, level=level, threads=runtime.decode_threads
        )
    if sliced is not None:
        volume = sliced
        if spec.input.pieces is not None:
            from engine.job.plans import refuse_out_of_core

            _close(source, volume)
            refuse_out_of_core(volume, "a scan's bone pieces (pieces)", "leave it out")
    elif pre is not None:
        volume = pre
    elif isinstance(source, Volume):
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
            level=level,
        )
    if spec.input.roi is not None:  # cropped before anything runs
        try:
            volume = _crop(volume, spec)
        except BaseException:
            _close(source, volume)
            raise
        if sliced is not None and whole is not None and volume.data.nbytes <= whole:  # the box fits: read it whole
            box: Any = volume.data  # engine.io.slabs.SlabSource
            volume = dataclasses.replace(volume, data=box.read(0, box.shape[0]))
            box.close()
    progress("loading", end)
    return volume


def _close(source: Any, volume: Volume) -> None:
    """The files of a scan read slab by slab (``engine.io.slabs``) closed, where this job opened them."""
    close = getattr(volume.data, "close", None)
    if not isinstance(source, Volume) and not isinstance(volume.data, np.ndarray) and close is not None:
        close()


def _crop(volume: Volume, spec: JobSpec) -> Volume:
    """The scan cropped to the roi, prepared whole first (``engine.job.plans.prepare_whole``: the slice filters and,
    on HU data, the bone outside the body dropped) where the box cuts the scan: the body outline of a box through
    the head would be cut open, its skull "outside the body". The bone inside the box is the whole model's."""
    from engine.job.plans import prepare_whole
    from engine.labels.pieces import crop_roi, roi_slices

    roi, orient = spec.input.roi, spec.recon.orient
    assert roi is not None
    sl = roi_slices(volume, roi, orient)  # refuses a box outside the scan before the whole is worked on
    if any(s.stop - s.start < n for s, n in zip(sl, volume.data.shape, strict=True)):
        volume = prepare_whole(volume, spec.recon)
    return crop_roi(volume, roi, orient)


def _scan(job: _Job, volume: Volume) -> JobResult:
    """The EMC33 pipeline and its files (the defect as one of its stages)."""
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    load_end, mesh_end = job.shares

    def within(stage: str, fraction: float) -> None:
        job.progress(stage, load_end + (mesh_end - load_end) * fraction)

    device, budget, recon = job.runtime.backend, job.runtime.budget, job.spec.recon
    on = job.runtime.device  # the backend, or several (the model's volume stages split over them)
    result = reconstruct(volume, recon, device=on, on_progress=within, max_device_bytes=budget)
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
    """A scan's largest bone pieces, each its own part, meshed from the scan's own values (``_piece_models``)."""
    from engine.job.plans import prepare_volume
    from engine.labels.pieces import bone_pieces

    assert job.spec.input.pieces is not None
    prepared = prepare_volume(volume, job.spec.recon)  # as the model sees the scan: bone of the body only
    lv = bone_pieces(prepared.volume, job.spec.recon, job.spec.input.pieces, level=prepared.choice.value)
    paths, report = _label_models(job, lv, lambda chosen: _piece_models(job, prepared.volume, chosen))
    return JobResult("pieces", paths, report, volume)


def _label_models(
    job: _Job, lv: Any, mesh: Callable[[Any], Any] | None = None
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Mesh every label (``engine.labels.parts.label_models``, or ``mesh`` for a scan's pieces) and write a label
    job's files."""
    import json

    from engine.export.files import REPORT_JSON
    from engine.labels.outputs import write_label_outputs
    from engine.labels.parts import label_models
    from engine.labels.pieces import select_segments

    spec, device = job.spec, job.runtime.backend
    if spec.input.segments:
        lv = select_segments(lv, list(spec.input.segments))
    job.progress("labels", job.shares[0])
    if mesh is not None:
        models = mesh(lv)
    else:
        models = label_models(lv, spec.recon, device=device, orient=spec.recon.orient)
    job.progress("writing", job.shares[1])
    extra = {"input": _label_input(lv)}
    paths = write_label_outputs(
        models, job.outdir, spec.recon, device=device, extra=extra, stl_folder=spec.outputs.label_stl_folder
    )
    return paths, json.loads(paths[REPORT_JSON].read_text())


def _piece_models(job: _Job, scan: Volume, lv: Any) -> Any:
    """Each piece of ``lv`` (``engine.labels.pieces.bone_pieces`` on the prepared ``scan``) meshed from the scan's
    own values, as the model is: the smoothed scan inside the piece's region (``engine.labels.pieces.PieceBox``)
    through the model's stages (MC33 at the model's level, decimation, islands, smoothing), so that its surface is
    the model's surface there. A piece that leaves nothing above the island size is a speck, left out and counted.
    Returns ``engine.labels.parts.LabelModels``."""
    from engine.errors import EmptySurfaceError
    from engine.job.pipeline import reconstruct
    from engine.labels.parts import LabelModels, file_names
    from engine.labels.pieces import piece_boxes
    from engine.orient import patient_frame

    recon, be, budget = job.spec.recon, job.runtime.backend, job.runtime.budget
    level = float(lv.source["level"])
    boxes = piece_boxes(lv, scan.data >= level)
    frame = patient_frame(scan, recon.orient)
    low = min(float(scan.data.min()), level) - 1.0  # outside a piece's region: below the level
    names = dict(zip((s.value for s in lv.segments), file_names(lv), strict=True))
    voxels = dict(zip((s.value for s in lv.segments), _piece_voxels(lv), strict=True))
    parts, rows, dropped = [], [], []
    for i, pb in enumerate(boxes):
        seg = lv.segment(pb.value)
        field = pb.masked(_smoothed(scan.data[pb.box], recon, be), low)
        piece = Volume(field, scan.spacing_zyx_mm, units=scan.units, source={"format": "piece", "piece": seg.name})
        params = _piece_params(recon, level, voxels[pb.value] / max(sum(voxels.values()), 1))
        try:
            rec = reconstruct(piece, params, device=be, max_device_bytes=budget)
        except EmptySurfaceError:  # nothing above the island size: a speck after all
            dropped.append({**seg.to_dict(), "reason": "below the island size once meshed"})
            continue
        part, row = _piece_part(rec, pb, seg, names[seg.value], frame, scan, voxels[pb.value])
        parts.append(part)
        rows.append(row)
        job.progress("labels", job.shares[0] + (job.shares[1] - job.shares[0]) * (i + 1) / len(boxes))
    if not parts:
        raise EmptySurfaceError("no bone piece gives a surface above the island size")
    return LabelModels(parts, _pieces_report(lv.source, rows, dropped, frame))


def _pieces_report(source: dict[str, Any], rows: list[Any], dropped: list[Any], frame: Any) -> dict[str, Any]:
    """A pieces job's report: its rows, the pieces left out, and, with fewer pieces than asked for (or picked by
    ``segments``), why: ``pieces.note``, and a ``fewer_pieces`` warning (shown by the page)."""
    from engine.labels.pieces import fewer_pieces_note

    source = {**source, "pieces_kept": len(rows), "specks_excluded": source["specks_excluded"] + len(dropped)}
    source.pop("note", None)
    wanted = len(source.get("segments_selected") or ()) or source["pieces_asked"]
    report = {
        "labels": rows,
        "labels_without_surface": dropped,
        "frame": frame.to_dict(),
        "labels_mesh": {"method": "the model's stages on the smoothed scan inside each piece's region"},
        "source": source,
        "pieces": {k: source.get(k) for k in _PIECES_KEYS if k in source},
    }
    if len(rows) < wanted:
        note = fewer_pieces_note(wanted, len(rows), source["specks_excluded"], source["speck_limit_mm3"])
        source["note"] = report["pieces"]["note"] = note
        report["warnings"] = [{"code": "fewer_pieces", "message": note}]
    return report


_PIECES_KEYS = ("pieces_asked", "pieces_found", "pieces_kept", "specks_excluded", "speck_limit_mm3")


def _piece_voxels(lv: Any) -> list[int]:
    """Each segment's voxels, in segment order."""
    import numpy as np

    counts = np.bincount(lv.labels.reshape(-1), minlength=max(s.value for s in lv.segments) + 1)
    return [int(counts[s.value]) for s in lv.segments]


def _smoothed(data: Any, recon: Any, be: Any) -> Any:
    """A box of the scan smoothed on the job's device as the model's Gaussian smooths it (float32 on the host);
    as it is where the model is not smoothed."""
    import numpy as np

    if recon.gaussian is None:
        return data.astype(np.float32)
    from engine.volume.gaussian import smooth_volume

    field = smooth_volume(be.from_host(np.ascontiguousarray(data)), recon.gaussian)
    return be.to_host(field).reshape(data.shape)


def _piece_params(recon: Any, level: float, share: float) -> Any:
    """The model's parameters for a piece's smoothed, masked field: no second Gaussian, preprocessing, body mask
    or defect; the model's level; islands by size only; a triangle cap shared by the piece's voxels."""
    from engine.params import MIN_TRIANGLES, DecimateParams, IslandParams, IsoParams

    dec = recon.decimate
    if dec is not None and dec.max_triangles is not None:
        dec = DecimateParams(reduction=None, max_triangles=max(MIN_TRIANGLES, round(dec.max_triangles * share)))
    islands = recon.islands
    if islands is not None:
        islands = IslandParams(min_volume_mm3=islands.min_volume_mm3, min_volume_voxels=islands.min_volume_voxels)
    iso = IsoParams(iso=level, closed=recon.iso.closed)
    return dataclasses.replace(
        recon, preprocess=None, gaussian=None, body=None, defect=None, iso=iso, islands=islands, decimate=dec
    )


def _piece_part(
    rec: Any, pb: Any, seg: Any, name: str, frame: Any, scan: Volume, voxels: int
) -> tuple[Any, dict[str, Any]]:
    """A meshed piece placed in the scan's patient frame (its box's corner added), and its report row."""
    import numpy as np

    from engine.labels.parts import LabelPart
    from engine.orient import to_patient
    from engine.types import Mesh

    mesh = rec.mesh
    corner = np.array([s.start * d for s, d in zip(pb.box, scan.spacing_zyx_mm, strict=True)], np.float32)
    placed = to_patient(Mesh(mesh.vertices + corner, mesh.faces), frame)
    stats = rec.report["mesh"]
    row = {
        "faces": int(stats["n_faces"]),
        "vertices": int(stats["n_vertices"]),
        "volume_mm3": float(stats["volume_mm3"]),
        "area_mm2": float(stats["area_mm2"]),
        "watertight": bool(stats["watertight"]),
        "components": int(stats["components"]),
        "voxels": voxels,
        "voxel_volume_mm3": voxels * float(np.prod(scan.spacing_zyx_mm)),
    }
    xyz = np.ascontiguousarray(placed.vertices[:, ::-1])
    part = LabelPart(seg.name, seg.value, seg.color, xyz, placed.faces, row)
    return part, {**seg.to_dict(), "file": f"labels/{name}.stl", **row}


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
