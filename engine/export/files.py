"""The output files of a job, in one registry (trimesh's one export registry): each file's name, kind, media type,
what it is for, the mesh it is made from (and so its triangle count in the report), which jobs have it and the
exporter of its format.

Everything that names output files reads ``FILES``: the writer (``engine.job.outputs``, ``engine.export.viewers``), the
exporters' table (``EXPORTERS``, re-exported by ``engine.export``), the storage (``core.storage``: only these
names are served), the worker (``worker.tasks``: each output's kind, media type and triangles; ``worker.pacs``:
``model.dcm``) and the API (``service.routes.files``: the download's media type; ``service.schemas`` and
``service.services``: each output's ``purpose``, which the page shows). The README's table "Which file for which
viewer" lists ``DEFAULT_FILES`` (``tests/engine/export/test_output_files.py`` holds them to each other).

Importing this module loads neither Warp nor numpy nor any exporter: an exporter is named as ``"module:function"``
and imported when asked for (``exporter_of``, ``EXPORTERS``), so the API and ``core`` read the registry freely.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from engine.report import Report

__all__ = [
    "DEFAULT_FILES",
    "DEFECT_JSON",
    "EXPORTERS",
    "FILES",
    "IMPLANT_STL",
    "LABELS_DCM",
    "LABELS_ZIP",
    "MODEL_DCM",
    "MODEL_GLB",
    "OPEN_STL",
    "PRINT_STL",
    "REPORT_JSON",
    "VIEWING_ENTRY",
    "Exporter",
    "MeshSource",
    "OutputFile",
    "When",
    "engine_files",
    "exporter_of",
    "move_files",
    "triangle_count",
    "viewing_files",
]

MeshSource = Literal["print", "phone", "ar", "implant"]
When = Literal["always", "closed", "open", "pacs", "defect", "labels"]
Exporter = Callable[..., bytes]

PRINT_STL = "model.stl"
OPEN_STL = "surface_open.stl"
MODEL_GLB = "model.glb"
REPORT_JSON = "report.json"
MODEL_DCM = "model.dcm"
IMPLANT_STL = "implant.stl"
DEFECT_JSON = "defect.json"
LABELS_ZIP = "labels.zip"
LABELS_DCM = "labels.dcm.zip"


@dataclass(frozen=True)
class OutputFile:
    """One output file of a job.

    Attributes:
        name: its name among the job's outputs (and in the report's ``exports``).
        kind: what the API calls it (``OutputFile.kind`` of the job resource).
        media_type: the Content-Type of its download.
        purpose: what it is for, in words: the README's table "Which file for which viewer" and the page's column.
        made_from: the mesh it is made from: the print model (``"print"``: the pipeline's mesh, in the patient
            frame), the phone copy or the AR copy (``"phone"``, ``"ar"``: ``engine.decimation.viewing``), the defect
            template (``"implant"``: ``engine.defect``); None for the reports.
        triangles: whether the job resource gives its triangle count (that of ``made_from``: ``triangle_count``);
            False for an image and the report.
        exporter: the exporter of its format as ``"module:function"`` (taking ``(vertices_zyx_mm, faces, ...)``,
            returning the file's bytes), imported only by ``exporter_of``; None for the report.
        when: which jobs have it: every job (``"always"``), a closed surface, the default (``"closed"``), an open
            surface (``"open"``, ``IsoParams.closed=False``), a PACS job (``"pacs"``: written by ``worker.pacs``,
            every other file by ``engine.job.outputs.write_outputs``), a job that asked for the defect (``"defect"``:
            ``ReconParams.defect``), a label job (``"labels"``: a segmentation, or a CT's bone ``pieces``;
            ``engine.labels.outputs.write_label_outputs``).
        parts: whether the exporter shows named parts beside the model (``engine.export.glb.Part``: the defect
            template as its own coloured node).
        labels: whether a label job has it too (its model.glb, phone.glb and ar.glb hold one named, coloured node
            per label; ``engine_files(labels=True)``).
        device: whether its exporter runs Warp kernels (the preview's rasteriser): ``engine.job.outputs`` runs it on
            the calling thread, and the exporters without (native codecs, numpy) in threads beside it.
    """

    name: str
    kind: str
    media_type: str
    purpose: str
    made_from: MeshSource | None
    triangles: bool
    exporter: str | None
    when: When = "always"
    parts: bool = False
    labels: bool = False
    device: bool = False

    @property
    def format(self) -> str | None:
        """The exporter's key in ``EXPORTERS`` (its function's name without ``to_``), or None."""
        return None if self.exporter is None else self.exporter.rpartition(":")[2].removeprefix("to_")


_GLB = "model/gltf-binary"
_FILES = (
    OutputFile(
        name=PRINT_STL,
        kind="print",
        media_type="model/stl",
        purpose="printers, CAD, slicers",
        made_from="print",
        triangles=True,
        exporter="engine.export.stl:to_stl",
        when="closed",
    ),
    OutputFile(
        name=OPEN_STL,
        kind="surface",
        media_type="model/stl",
        purpose="an open surface: CAD and measurement, not printing",
        made_from="print",
        triangles=True,
        exporter="engine.export.stl:to_stl",
        when="open",
    ),
    OutputFile(
        name=MODEL_GLB,
        kind="model",
        media_type=_GLB,
        purpose="desktop viewers, full detail",
        made_from="print",
        triangles=True,
        exporter="engine.export.glb:to_glb",
        parts=True,
        labels=True,
    ),
    OutputFile(
        name="phone.glb",
        kind="phone",
        media_type=_GLB,
        purpose="the phone app, three.js/model-viewer/Babylon with the Draco decoder",
        made_from="phone",
        triangles=True,
        exporter="engine.export.draco:to_draco_glb",
        parts=True,
        labels=True,
    ),
    OutputFile(
        name="ar.glb",
        kind="ar",
        media_type=_GLB,
        purpose="Android Scene Viewer (AR)",
        made_from="ar",
        triangles=True,
        exporter="engine.export.glb:to_glb",
        parts=True,
        labels=True,
    ),
    OutputFile(
        name="phone_meshopt.glb",
        kind="phone_meshopt",
        media_type=_GLB,
        purpose="three.js, model-viewer, Babylon.js without Draco's WASM",
        made_from="phone",
        triangles=True,
        exporter="engine.export.meshopt:to_meshopt_glb",
    ),
    OutputFile(
        name="model.usdz",
        kind="ar_ios",
        media_type="model/vnd.usdz+zip",
        purpose="iOS / iPadOS AR Quick Look",
        made_from="ar",
        triangles=True,
        exporter="engine.export.usdz:to_usdz",
    ),
    OutputFile(
        name="preview.png",
        kind="preview",
        media_type="image/png",
        purpose="app lists, the page's job list",
        made_from="phone",
        triangles=False,
        exporter="engine.export.preview:to_preview_png",
        labels=True,
        device=True,
    ),
    OutputFile(
        name=REPORT_JSON,
        kind="report",
        media_type="application/json",
        purpose="people and scripts",
        made_from=None,
        triangles=False,
        exporter=None,
        labels=True,
    ),
    OutputFile(
        name=MODEL_DCM,
        kind="dicom",
        media_type="application/dicom",
        purpose="the hospital's PACS (Encapsulated STL of the print model)",
        made_from="print",
        triangles=True,
        exporter="engine.export.dicom_stl:to_encapsulated_stl",
        when="pacs",
    ),
    OutputFile(
        name=IMPLANT_STL,
        kind="implant",
        media_type="model/stl",
        purpose="the defect's mirrored fill template: printers, CAD (patient frame of model.stl, mm)",
        made_from="implant",
        triangles=True,
        exporter="engine.export.stl:to_stl",
        when="defect",
    ),
    OutputFile(
        name=DEFECT_JSON,
        kind="defect",
        media_type="application/json",
        purpose="the defect's size, place and symmetry plane, or why none was made",
        made_from=None,
        triangles=False,
        exporter=None,
        when="defect",
    ),
    OutputFile(
        name=LABELS_ZIP,
        kind="labels",
        media_type="application/zip",
        purpose="one watertight STL per label (labels/<name>.stl, patient LPS mm): printers, CAD",
        made_from="print",
        triangles=True,
        exporter=None,
        when="labels",
    ),
    OutputFile(
        name=LABELS_DCM,
        kind="labels_dicom",
        media_type="application/zip",
        purpose="the hospital's PACS: one Encapsulated STL per label (a label job from the PACS)",
        made_from="print",
        triangles=True,
        exporter=None,
        when="pacs",
    ),
)
FILES: Mapping[str, OutputFile] = MappingProxyType({f.name: f for f in _FILES})
# where the report keeps the account of each viewing copy (``exports``), and so its triangle count
VIEWING_ENTRY: Mapping[MeshSource, str] = MappingProxyType({"phone": "phone.glb", "ar": "ar.glb"})


def engine_files(closed: bool = True, defect: bool = False, labels: bool = False) -> tuple[str, ...]:
    """The files ``engine.job.outputs.write_outputs`` writes, in order, for a closed surface (the print model
    ``model.stl``) or an open one (``surface_open.stl``), with the defect's (``defect.json``; ``implant.stl``
    when a template was made) when asked; with ``labels``, those of a label job instead
    (``engine.labels.outputs.write_label_outputs``: the files marked ``labels`` and ``labels.zip``)."""
    if labels:
        return tuple(f.name for f in _FILES if f.labels or f.when == "labels")
    wanted = ("always", "closed" if closed else "open", *(("defect",) if defect else ()))
    return tuple(f.name for f in _FILES if f.when in wanted)


DEFAULT_FILES = engine_files(closed=True)  # a default job's files: the README's table "Which file for which viewer"


def move_files(src: Path, dest: Path, names: Iterable[str]) -> dict[str, Path]:
    """Rename each file of ``names`` from the writer's temporary folder ``src`` into ``dest`` (one rename each: a
    reader sees a whole file or none); returns {name: its path in ``dest``}, in ``names``' order."""
    paths = {}
    for name in names:
        os.replace(src / name, dest / name)
        paths[name] = dest / name
    return paths


def viewing_files() -> tuple[OutputFile, ...]:
    """The files made from the viewing copies (the phone and AR meshes), in the order they are encoded."""
    return tuple(f for f in _FILES if f.made_from in VIEWING_ENTRY)


def exporter_of(file: str | OutputFile) -> Exporter:
    """The exporter of a file (by name or entry), imported now with the native libraries it loads (``_resolve``).

    Raises:
        KeyError: not an output file, or one without an exporter (the report).
    """
    entry = FILES[file] if isinstance(file, str) else file
    if entry.exporter is None:
        raise KeyError(f"{entry.name} has no exporter")
    return _resolve(entry.exporter)


def load_exporters(files: Iterable[OutputFile]) -> None:
    """Look up the exporters of ``files`` now (``exporter_of``: with their native libraries), on this thread, before
    any thread is started that could load a native library at the same time."""
    for entry in files:
        if entry.exporter is not None:
            _resolve(entry.exporter)


def _resolve(path: str) -> Exporter:
    """The exporter ``module:function``, its module imported with the native libraries it loads lazily (its
    ``load_native``), on the calling thread. A native library's first load from two threads at once can deadlock:
    USD's initialisers take the GIL inside ``dlopen`` (holding the loader's lock) while a thread holding the GIL
    waits in ``dlopen`` for that lock (ctypes loading meshoptimizer's library). That hung
    ``engine.job.outputs.write_outputs`` on the H100 host once and in the tests here; its threads encode with exporters
    looked up before they start."""
    name, _, function = path.partition(":")
    module = importlib.import_module(name)
    load_native = getattr(module, "load_native", None)
    if load_native is not None:
        load_native()
    fn: Exporter = getattr(module, function)
    return fn


class _Exporters(Mapping[str, Exporter]):
    """The exporters by format (``"stl"``, ``"glb"``, ``"draco_glb"``, ...), each imported on first access."""

    def __init__(self, files: tuple[OutputFile, ...]) -> None:
        self._paths = {f.format: f.exporter for f in files if f.format is not None and f.exporter is not None}

    def __getitem__(self, key: str) -> Exporter:
        return _resolve(self._paths[key])

    def __iter__(self) -> Iterator[str]:
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)

    def __repr__(self) -> str:
        return f"EXPORTERS({', '.join(self._paths)})"


EXPORTERS: Mapping[str, Exporter] = _Exporters(_FILES)


def triangle_count(name: str, report: Report) -> int | None:
    """The triangles of output file ``name`` by the report: the print model's (``mesh.n_faces``) or its viewing
    copy's (``exports["phone.glb" | "ar.glb"].faces``; a label job's print model is all its labels: model.glb
    and labels.zip); None for a file without triangles or not in the registry."""
    entry = FILES.get(name)
    if entry is None or not entry.triangles or entry.made_from is None:
        return None
    if entry.made_from == "print":
        return report["mesh"]["n_faces"]
    if entry.made_from == "implant":
        return report.get("defect", {}).get("implant_faces")
    return report["exports"][VIEWING_ENTRY[entry.made_from]]["faces"]
