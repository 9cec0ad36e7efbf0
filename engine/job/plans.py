"""The two plans of ``engine.job.pipeline.reconstruct``, chosen once from the memory budget (``engine.budget``): each an
ordered tuple of named stages over a small typed state (``State``).

* ``WHOLE_VOLUME`` (no budget): the volume goes up once, the Gaussian and MC33 run on the whole field, the mesh is
  decimated in one piece;
* ``STREAMED`` (a budget): the volume stays on the host (or on disk, read slab by slab under a host memory bound:
  ``engine.io.slabs``, ``out_of_core``) and streams through the Gaussian and MC33 in z slabs
  (``engine.isosurface.stream``), a mesh whose decimation does not fit is decimated in groups of slabs and
  finished across their borders (``engine.decimation.groups``), and the finishing stages go to the host where the
  model does not fit (``Budget.place``).

Both plans have the same stage names (``STAGES``), so the report and the progress read the same. Each stage is
``stage(state, params, report, progress)``, writing its blocks of the report (``engine.report.Report``);
everything after preprocess runs on the device where the data already is.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.budget import Budget
from engine.errors import EmptySurfaceError, InputError, StageError
from engine.level import LevelChoice, model_warnings, resolve_level
from engine.params import ReconParams
from engine.report import Report
from engine.types import Volume

SEAM_VOXELS = 6  # a budgeted decimation's last pass across the slab groups' borders reaches this far from them
Progress = Callable[[float], None]


@dataclass
class State:
    """What the stages hand on: the volume, then the device field, then the device mesh (and its stars)."""

    volume: Volume
    budget: Budget = field(default_factory=Budget)  # every stage keeps to it (the streamed plan)
    backend: Any = None  # engine.backend.Backend the device stages run on (Warp's, or OpenCL's)
    devices: tuple[Any, ...] = ()  # a job over several devices: their backends (``backend`` the first), each with
    # the budget; the streamed volume stages and the groups' decimation split over them (engine.isosurface.multi)
    field: Any = None
    level: float = 0.0
    pos: Any = None  # the backend's VEC3F array (wp.array(dtype=wp.vec3) on Warp), (z, y, x) mm
    faces: Any = None  # the backend's VEC3I array
    incidence: Any = None  # devmesh.Incidence of the current mesh, when built
    normals: Any = None
    stream: Any = None  # engine.isosurface.stream.StreamResult of the streamed plan
    choice: LevelChoice | None = None  # the level and the HU offset (engine.level), chosen once in preprocess
    warnings: Future[list[dict[str, Any]]] | None = None  # model_warnings, measured beside the device stages

    def incidence_built(self) -> Any:
        """The current mesh's stars (``engine.surface.devmesh.Incidence``), built once."""
        from engine.surface.devmesh import Incidence

        if self.incidence is None:
            self.incidence = Incidence(len(self.pos)).build(self.faces, len(self.faces))
        return self.incidence


Stage = Callable[[State, ReconParams, Report, Progress], None]


@dataclass
class Prepared:
    """The scan as the model sees it (``prepare_volume``): preprocessed and, on HU data, bone of the body only; the
    level chosen once; the body mask's report (None without one)."""

    volume: Volume
    choice: LevelChoice
    body: dict[str, Any] | None


# a roi crop's source key: the scan was prepared on the whole before the crop (``engine.job.run``, ``prepare_whole``)
PREPARED_WHOLE = "prepared_whole"


def out_of_core(volume: Volume) -> bool:
    """Whether the scan is read slab by slab from disk (``engine.io.slabs.SlabSource``: a host memory bound) rather
    than held as an array."""
    return not isinstance(volume.data, np.ndarray)


def refuse_out_of_core(volume: Volume, what: str, way_out: str) -> None:
    """Raise the plain-words ``InputError`` of a step that needs the whole scan in memory, out of core.

    Raises:
        InputError: always: ``what`` needs the whole scan, and ``way_out`` avoids it.
    """
    from engine.budget import mib

    raise InputError(
        f"{what} needs the whole scan in memory, and the scan ({mib(volume.data.nbytes)} of voxels) is over the "
        f"host memory bound's share for a whole scan, so it is read slab by slab: {way_out}, or give a "
        f"--max-host-bytes of at least {mib(2 * volume.data.nbytes + (1 << 20))}"
    )


def prepare_volume(volume: Volume, params: ReconParams) -> Prepared:
    """The paper's slice preprocessing (when asked), the level (given, a preset, or automatic: ``engine.level``) and
    the bone inside the body outline (``params.body``, HU data: ``engine.volume.bodymask``): what the model and the
    defect (the pipeline's stage and ``bonemesh defect`` alike) are made from.

    A region of interest cropped from a scan prepared whole (``prepare_whole``: its ``source`` holds
    ``PREPARED_WHOLE``) is not preprocessed or outlined again: a box through the head cuts the body outline open,
    and the skull inside it would lie "outside the body"; its body report is the whole scan's."""
    from engine.volume.preprocess import preprocess_volume

    whole = volume.source.get(PREPARED_WHOLE)
    sliced = out_of_core(volume)
    if params.preprocess is not None and whole is None:
        if sliced:
            refuse_out_of_core(volume, "the slice preprocessing (--threshold & co.)", "leave it out")
        volume = preprocess_volume(volume, params.preprocess)
    choice = resolve_level(volume, params)  # out of core: from strided samples read plane by plane, the same
    body = None
    if whole is not None:
        body = whole.get("body_mask")
    elif params.body is not None:
        from engine.volume.bodymask import isolate_bone

        if sliced and choice.hu_offset is not None and choice.value > params.body.outline_hu + choice.hu_offset:
            refuse_out_of_core(volume, "the body mask (bone outside the body outline)", "give --keep-outside-body")
        volume, body = isolate_bone(volume, choice.value, params.body, choice.hu_offset)
    return Prepared(volume, choice, body)


def prepare_whole(volume: Volume, params: ReconParams) -> Volume:
    """The scan preprocessed and outlined whole (``prepare_volume``), for a region of interest to be cropped from
    next (``engine.labels.pieces.crop_roi``); its ``source`` says so (``PREPARED_WHOLE``: the body report, with
    ``outlined_on``), and ``prepare_volume`` then leaves the crop as it is. Nothing is done (the same volume) where
    neither the preprocessing nor the body mask is asked for."""
    if params.preprocess is None and params.body is None:
        return volume
    prepared = prepare_volume(volume, params)
    body = prepared.body
    if body is not None and body.get("applied"):
        body = {**body, "outlined_on": f"the whole scan {list(volume.data.shape)} (z, y, x), before the roi crop"}
    mark = {"preprocessed": params.preprocess is not None, "body_mask": body}
    return dataclasses.replace(prepared.volume, source={**prepared.volume.source, PREPARED_WHOLE: mark})


def _preprocess(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    from engine.orient import patient_frame

    prepared = prepare_volume(st.volume, params)
    report["counts"]["voxels"] = int(prepared.volume.data.size)
    report["frame"] = patient_frame(prepared.volume, params.orient).to_dict()  # engine.orient: STL/glTF frames
    st.volume, st.choice = prepared.volume, prepared.choice
    if prepared.body is not None:
        report["body_mask"] = prepared.body
    # voxel size order, a skin surface (engine.level): host work on a sample of the scan (0.05 s for the 1 G voxel
    # phantom on an H200 host), measured on a thread while the device stages run; ``join_warnings`` reports them
    report["warnings"] = []
    if out_of_core(st.volume):  # its samples are read from the same slab source as the stages: not beside them
        report["warnings"] = model_warnings(st.volume, st.choice)
    else:
        st.warnings = _HOST_WORK.submit(model_warnings, st.volume, st.choice)


_HOST_WORK = ThreadPoolExecutor(1, thread_name_prefix="bonemesh-warnings")


def join_warnings(st: State, report: Report) -> None:
    """The model's warnings into the report, once the thread measuring them is done (its error raised here)."""
    if st.warnings is None:
        return
    future, st.warnings = st.warnings, None
    try:
        report["warnings"] = future.result()
    except Exception as exc:  # as the preprocess stage's own failure would have been
        raise StageError("preprocess", exc) from exc


def _upload(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    """The volume to the device, once (the whole-volume plan)."""
    st.field = st.backend.from_host(np.ascontiguousarray(_device_dtype(st.volume.data)))
    _choose_level(st, params, report)


def _stage_on_host(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    """The volume stays on the host, contiguous, to stream in slabs (the streamed plan: engine.isosurface.stream);
    out of core, on disk (read slab by slab: its planes are of a type the device reads already)."""
    if not out_of_core(st.volume):
        st.volume = dataclasses.replace(st.volume, data=np.ascontiguousarray(_device_dtype(st.volume.data)))
    _choose_level(st, params, report)


def _device_dtype(data: np.ndarray) -> np.ndarray:
    """The samples in a type the device stages read (uint8, uint16, int16 or float32), else as float32."""
    if data.dtype not in (np.uint8, np.uint16, np.int16, np.float32):
        data = data.astype(np.float32)
    return data


def _choose_level(st: State, params: ReconParams, report: Report) -> None:
    choice = st.choice or resolve_level(st.volume, params)
    st.level = choice.value
    report["iso_level"] = choice.report(st.volume.units)


def _gaussian(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    from engine.volume.gaussian import smooth_volume

    if params.gaussian is not None:
        st.field = smooth_volume(st.field, params.gaussian)


def _gaussian_in_slabs(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    """Nothing here: the streamed plan smooths slab by slab inside its isosurface stage."""


def _isosurface(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    from engine.isosurface.mc33 import extract_isosurface
    from engine.isosurface.stats import IsosurfaceStats

    stats = IsosurfaceStats()
    with _data_errors():  # its ValueErrors are about the data (NaN, checked on the device in the extraction's pass)
        v, f = extract_isosurface(
            st.field, st.level, spacing=st.volume.spacing_zyx_mm, closed=params.iso.closed, stats=stats
        )
    st.field = None
    _take_surface(st, v, f, stats, report)


def _isosurface_streamed(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    from engine.isosurface.stats import IsosurfaceStats

    stats = IsosurfaceStats()
    with _data_errors():
        v, f = _stream(st, params, stats)
    if st.stream.grouped:  # decimated in groups already
        report["counts"]["isosurface"] = {"vertices": st.stream.mc33_vertices, "faces": st.stream.mc33_faces}
        report["isosurface"] = {"slabs": stats.slabs, "active_blocks": stats.active_blocks, "blocks": stats.blocks}
        return
    _take_surface(st, v, f, stats, report)


@contextmanager
def _data_errors() -> Iterator[None]:
    """The isosurface's ``ValueError`` (about the data: NaN) as an ``InputError``; an ``InputError`` as it is."""
    try:
        yield
    except InputError:
        raise
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _take_surface(st: State, v: Any, f: Any, stats: Any, report: Report) -> None:
    """The isosurface becomes the state's mesh; an empty one is ``EmptySurfaceError``."""
    if len(f) == 0:
        lo, hi = float(st.volume.data.min()), float(st.volume.data.max())
        raise EmptySurfaceError(
            f"no surface at level {st.level:g} {st.volume.units}: the scan's values run from "
            f"{lo:g} to {hi:g}; choose a level inside that range"
        )
    st.pos, st.faces = v, f
    report["counts"]["isosurface"] = {"vertices": len(v), "faces": len(f)}
    report["isosurface"] = {"slabs": stats.slabs, "active_blocks": stats.active_blocks, "blocks": stats.blocks}


def _stream(st: State, params: ReconParams, stats: Any) -> tuple[Any, Any]:
    """The Gaussian and MC33 within the budget (``engine.isosurface.stream``): the device mesh, or (when groups of
    slabs had to be decimated on the way) empty arrays and the groups in ``st.stream``."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.isosurface.stream import stream_surface

    dec = params.decimate
    if len(st.devices) > 1 and dec is not None:  # over several devices: always in groups, then joined
        from engine.isosurface.multi import stream_parts

        st.stream = stream_parts(
            st.volume.data, st.level, st.volume.spacing_zyx_mm, closed=params.iso.closed, gaussian=params.gaussian,
            budget=st.budget, ratio=dec.reduction, devices=st.devices, stats=stats,
        )  # fmt: skip
        return st.backend.empty(0, VEC3F), st.backend.empty(0, VEC3I)
    st.stream = stream_surface(
        st.volume.data,
        st.level,
        st.volume.spacing_zyx_mm,
        closed=params.iso.closed,
        gaussian=params.gaussian,
        budget=st.budget,
        ratio=None if dec is None else dec.reduction,
        decimate=dec is not None,
        dev=st.backend,
        stats=stats,
    )
    if st.stream.device is not None:
        device_mesh: tuple[Any, Any] = st.stream.device
        return device_mesh
    return st.backend.empty(0, VEC3F), st.backend.empty(0, VEC3I)


def _decimate(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    if params.decimate is None:
        return
    from engine.decimation.passes import TOLERANCE, decimate_device

    n_in = len(st.faces)
    target = params.decimate.target_faces(n_in)
    if target >= n_in:
        report["decimate"] = {"input_faces": n_in, "target_faces": target, "output_faces": n_in, "passes": 0}
        return

    def on_pass(faces_now: int) -> None:
        progress((n_in - faces_now) / max(n_in - target, 1))

    st.pos, st.faces, stats = decimate_device(st.pos, st.faces, target, on_pass=on_pass)
    info = stats.to_dict()
    info["achieved_ratio"] = stats.output_faces / n_in
    info["limited_by_guards"] = stats.output_faces > target * (1 + TOLERANCE)
    info["method"] = f"{_kind(st)} quadric edge collapse (link condition, border kept, normal turn guard)"
    report["decimate"] = info
    report["counts"]["decimate"] = {"vertices": len(st.pos), "faces": stats.output_faces}


def _decimate_streamed(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    if st.stream.grouped:
        _decimate_groups(st, params, report)
    else:
        _decimate(st, params, report, progress)


def _decimate_groups(st: State, params: ReconParams, report: Report) -> None:
    """Finish a decimation begun in groups of slabs: tiled rounds across their borders, then a last pass."""
    from engine.decimation.groups import finish_groups
    from engine.decimation.passes import TOLERANCE

    sr = st.stream
    assert params.decimate is not None and sr is not None and sr.grouped
    n_in = sr.mc33_faces
    target = params.decimate.target_faces(n_in)
    host, sr.host = sr.host, None
    pieces, sr.pieces = (None if sr.pieces is None else list(sr.pieces)), None  # finish_groups takes them over
    seam_mm = SEAM_VOXELS * max(st.volume.spacing_zyx_mm)
    device = st.backend if st.backend.kind != "warp" else None  # Warp: where the groups are (as before)
    st.pos, st.faces, info = finish_groups(host, pieces, sr.origin, target, st.budget, sr.borders, seam_mm, device)
    out = len(st.faces)
    info |= {"input_faces": n_in, "target_faces": target, "achieved_ratio": out / n_in}
    info["limited_by_guards"] = out > target * (1 + TOLERANCE)
    info["method"] = f"{_kind(st)} quadric edge collapse in slab groups and z tiles with pinned borders (memory budget)"
    report["decimate"] = info
    report["counts"]["decimate"] = {"vertices": len(st.pos), "faces": out}


def _kind(st: State) -> str:
    """The backend the mesh is on, in words for the report ("warp", "opencl")."""
    from engine.backend.select import backend_of

    return str(backend_of(st.faces).kind) if st.faces is not None else str(st.backend.kind)


def _fit_or_host(st: State, report: Report) -> None:
    """The finishing stages hold the whole final mesh: within a budget it cannot fit, they run on the host
    (``Budget.place``: Warp's CPU device, outside the budget; reported as ``report["finish"]``), or, where
    the device is the host, the job stops early with the budget that would work."""
    from engine.backend.select import backend_of
    from engine.surface.devmesh import on_device

    what = f"finishing the model ({len(st.faces):,} faces: islands, smoothing, normals, outputs)"
    need = st.budget.costs.finish_bytes(len(st.faces))
    where, note = st.budget.place(backend_of(st.faces), need, what, " or decimate further")
    if note is not None:
        st.pos, st.faces = on_device(where, st.pos, st.faces)
        st.incidence = None
        report["finish"] = note


def _islands(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    if params.islands is None:
        return
    from engine.surface.islands import remove_islands_device

    min_volume = params.islands.min_volume_for(st.volume.spacing_zyx_mm)
    st.pos, st.faces, info = remove_islands_device(
        st.pos, st.faces, min_volume_mm3=min_volume, keep_largest=params.islands.keep_largest, consume=True
    )
    if len(st.faces) == 0:
        raise EmptySurfaceError("island removal left nothing: lower --min-island-mm3 or keep more pieces")
    report["islands"] = {**info, "min_volume_mm3": min_volume}
    report["counts"]["islands"] = {"vertices": len(st.pos), "faces": len(st.faces)}


def _islands_within(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    """Islands within the budget: the finishing stages first go to the host where the model does not fit."""
    _fit_or_host(st, report)
    _islands(st, params, report, progress)


def _smooth(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    if params.smooth is None:
        return
    from engine.surface.smooth import smooth_device

    st.pos, report["smooth"] = smooth_device(st.pos, st.faces, params.smooth, st.incidence_built())


def _normals(st: State, params: ReconParams, report: Report, progress: Progress) -> None:
    from engine.surface.normals import normals_device

    st.normals = normals_device(st.pos, st.faces, st.incidence_built())


WHOLE_VOLUME: tuple[tuple[str, Stage], ...] = (
    ("preprocess", _preprocess),
    ("upload", _upload),
    ("gaussian", _gaussian),
    ("isosurface", _isosurface),
    ("decimate", _decimate),
    ("islands", _islands),
    ("smooth", _smooth),
    ("normals", _normals),
)
STREAMED: tuple[tuple[str, Stage], ...] = (
    ("preprocess", _preprocess),
    ("upload", _stage_on_host),
    ("gaussian", _gaussian_in_slabs),
    ("isosurface", _isosurface_streamed),
    ("decimate", _decimate_streamed),
    ("islands", _islands_within),
    ("smooth", _smooth),
    ("normals", _normals),
)
STAGES = tuple(name for name, _ in WHOLE_VOLUME)
assert STAGES == tuple(name for name, _ in STREAMED)


def plan_for(budget: Budget) -> tuple[tuple[str, Stage], ...]:
    """The plan a budget asks for: ``STREAMED`` within a budget, else ``WHOLE_VOLUME``."""
    return STREAMED if budget.limited else WHOLE_VOLUME
