"""The shape of a reconstruction's report (``report.json``): one declared type that its writers
(``engine.job.pipeline`` and its ``engine.job.plans``, ``engine.job.outputs``) and its readers (``engine.cli``'s
summary, ``engine.export.files``' triangle counts for ``worker.tasks``, ``engine.paper``) share, checked by mypy.

The report stays a plain ``dict`` at run time (``TypedDict``s): ``report.json`` is ``json.dumps`` of it, so its keys,
their order and its structure are what clients have always read. ``reconstruct`` fills the blocks marked below as
``reconstruct``; ``write_outputs`` adds ``layout``, ``print_check``, ``exports`` and ``write_seconds`` and the glTF
centre to ``frame``. Blocks whose content is a stage's own account (``decimate``, ``smooth``, ``islands``,
``body_mask``, ``input.source``, ``parameters``) are typed as JSON objects: their keys belong to that stage.

Importing this module loads nothing but the standard library's ``json``, ``pathlib`` and ``typing`` (``core`` and
``service`` read it through ``engine.export.files``).
"""

from __future__ import annotations

import json
from pathlib import PurePath
from typing import Any, NotRequired, TypedDict

__all__ = [
    "Bounds",
    "DeviceInfo",
    "ExportInfo",
    "FaceCount",
    "FrameInfo",
    "InputInfo",
    "IsoLevel",
    "IsosurfaceInfo",
    "MemoryInfo",
    "MeshStats",
    "Placement",
    "PrintCheck",
    "Report",
    "report_json",
]


class DeviceInfo(TypedDict):
    """Where the pipeline ran: the caller's spec, the device's name (Warp's ``cuda:0``, or the OpenCL device's
    ``opencl:N`` label), its description and the backend (``"warp"`` or ``"opencl"``: ``engine.backend``); a job
    over several devices lists them (``devices``: the first is ``name``'s, ``engine.isosurface.multi``)."""

    spec: str
    name: str
    description: str
    backend: str
    devices: NotRequired[list[str]]


class InputInfo(TypedDict):
    """The volume as the pipeline received it; ``source``: the loader's account (files, completeness, series)."""

    shape_zyx: list[int]
    dtype: str
    spacing_zyx_mm: list[float]
    units: str
    source: dict[str, Any]


class FaceCount(TypedDict):
    """A mesh's size after a stage (``counts``)."""

    vertices: int
    faces: int


class Counts(TypedDict, total=False):
    """Sizes along the way: the voxels read, and the mesh after each stage that changes it."""

    voxels: int
    isosurface: FaceCount
    decimate: FaceCount
    islands: FaceCount


class FrameInfo(TypedDict):
    """Where the model lies (``engine.orient.Frame.to_dict``): the STL's and glTF files' frames in words, how the
    placement is known, the grid -> patient map (4x4 on grid (x, y, z, 1) mm); ``write_outputs`` adds the glTF
    files' centre (patient LPS mm)."""

    stl: str
    gltf: str
    placed_by: str
    patient_from_grid_xyz: list[list[float]]
    gltf_centre_lps_mm: NotRequired[list[float]]


class IsoLevel(TypedDict):
    """The iso level used, in the volume's units, and how it was chosen (given, a preset, Otsu); how stored values
    relate to HU (``hu_offset``: stored = HU + it, None: unknown; ``hu_offset_from``: "HU data", "given",
    "detected" or None) and, when detected, the histogram's evidence (``engine.level.LevelChoice``)."""

    value: float
    units: str
    chosen_by: str
    hu_offset: NotRequired[float | None]
    hu_offset_from: NotRequired[str | None]
    hu_offset_detected: NotRequired[dict[str, float]]


class IsosurfaceInfo(TypedDict):
    """The MC33 pass: its z slabs, and the blocks it visited out of all."""

    slabs: int
    active_blocks: int
    blocks: int


class Bounds(TypedDict):
    """An axis-aligned box, (x, y, z) mm."""

    min: list[float]
    max: list[float]


class MeshStats(TypedDict):
    """The finished mesh's diagnostics (``engine.surface.mesh_stats`` / ``mesh_stats_device``: same keys)."""

    n_vertices: int
    n_faces: int
    n_edges: int
    watertight: bool
    manifold: bool
    vertex_manifold: bool | None
    boundary_edges: int
    nonmanifold_edges: int
    inconsistent_edges: int
    degenerate_faces: int
    components: int
    euler: int
    volume_mm3: float
    area_mm2: float
    bbox_mm: Bounds | None


class Placement(TypedDict):
    """Where work ran (``engine.budget.Budget.place``): the device, and why it is the host where the budget sent it
    there."""

    device: str
    reason: NotRequired[str]


class MemoryInfo(TypedDict):
    """The device memory budget (bytes, None: none) and the peak the run used beyond what was in use before it
    (``engine.backend.memory.PeakMemory``); ``stream``: the streamed plan's account; under a host memory bound,
    the bound (``host_bound_bytes``) and whether the scan was read slab by slab from disk (``out_of_core``)."""

    budget_bytes: int | None
    peak_bytes: int | None
    measured_by: str
    in_use_before_bytes: int
    stream: NotRequired[dict[str, Any]]
    host_bound_bytes: NotRequired[int]
    out_of_core: NotRequired[bool]


class PrintCheck(TypedDict):
    """The print model's check passed (``engine.export.printcheck``): the checks made and the faces checked."""

    passed: bool
    checks: list[str]
    faces: int


class ExportInfo(TypedDict, total=False):
    """One output file in ``exports`` (keyed by file name): its ``bytes``; for the viewing copies (``phone.glb``,
    ``ar.glb``) also how the copy was made (``engine.decimation.viewing``): its ``faces``, whether it was
    ``decimated``, and where it was, the passes, the pieces dropped, whether the topology was kept, the clustering."""

    bytes: int
    faces: int
    decimated: bool
    topology_preserved: bool
    passes: int
    pieces_dropped: int
    over_budget: bool
    clustered: dict[str, Any]
    taken_to: dict[str, Any]
    tiled_for_clustering: dict[str, Any]


class Report(TypedDict):
    """``report.json``. The first six blocks exist from the start of ``reconstruct``; the others are added by the
    stage or writer named beside them, some only when it ran (``body_mask``, ``decimate``, ``finish``, ``islands``,
    ``smooth``, ``print_check``)."""

    parameters: dict[str, Any]  # ReconParams.to_dict()
    device: DeviceInfo
    versions: dict[str, str]
    input: InputInfo
    stage_seconds: dict[str, float]  # per stage, in order (engine.job.plans.STAGES)
    counts: Counts
    frame: NotRequired[FrameInfo]  # preprocess; write_outputs adds the glTF centre
    body_mask: NotRequired[dict[str, Any]]  # preprocess, HU data (engine.volume.bodymask)
    # preprocess: what a person should check, each {"code", "message", ...measures} (engine.level.model_warnings):
    # "voxel_size_order" (a given voxel size looks swapped), "looks_like_skin" (the level makes a skin surface),
    # "maybe_hu_offset" (an automatic Otsu level on a stack that may be HU + 1024)
    warnings: NotRequired[list[dict[str, Any]]]
    iso_level: NotRequired[IsoLevel]  # upload
    isosurface: NotRequired[IsosurfaceInfo]
    decimate: NotRequired[dict[str, Any]]  # the decimation's statistics (engine.decimation)
    finish: NotRequired[Placement]  # the finishing stages sent to the host by the budget
    islands: NotRequired[dict[str, Any]]  # speck removal (engine.surface.islands)
    smooth: NotRequired[dict[str, Any]]  # engine.surface.smooth
    mesh: NotRequired[MeshStats]  # the finished mesh
    finish_seconds: NotRequired[float]
    memory: NotRequired[MemoryInfo]
    total_seconds: NotRequired[float]
    layout: NotRequired[Placement]  # write_outputs: where the model was laid out for its files
    print_check: NotRequired[PrintCheck]  # write_outputs, a closed surface (model.stl)
    exports: NotRequired[dict[str, ExportInfo]]  # write_outputs: every file but report.json, by name
    write_seconds: NotRequired[dict[str, float | dict[str, float]]]  # write_outputs (encode_parts: per file)
    defect: NotRequired[dict[str, Any]]  # ReconParams.defect: found or refused (engine.defect.step.DefectOutcome)
    reoriented: NotRequired[dict[str, Any]]  # engine.job.reorient: {"from": OrientParams, "to": OrientParams} as dicts


def report_json(report: Report) -> str:
    """``report.json``'s text: the report indented by two, numpy scalars and arrays as numbers and lists, paths as
    text, with a final newline."""
    return json.dumps(report, indent=2, default=_json_default) + "\n"


def _json_default(obj: Any) -> Any:
    import numpy as np  # reached only for what json cannot write itself

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, PurePath):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
