"""Turn a finished model into another stack orientation without reconstructing it (``bonemesh orient``, the API's
``POST /v1/jobs/{id}/orient``).

An image stack carries no orientation: ``OrientParams`` (first slice, flips) place it in the patient frame
(``engine.orient.patient_frame``). When the model comes out upside down, facing backwards or mirrored, the mesh is
right and only its placement is wrong. ``reorient`` reads the print model back (``model.stl``: the exact float32
patient positions; ``model.glb``: the same mesh indexed, with its normals, in the pipeline's vertex order), takes
it back to the grid through the report's frame, and writes every output again (``engine.job.outputs.write_outputs``)
with the frame of the new ``OrientParams``: the same files as reconstructing with those params, up to float
rounding. ``report.json`` keeps every block but the frame (the new one), ``parameters.orient`` (the new params),
``reoriented`` (from which orientation, when) and what ``write_outputs`` writes again. The files are written into
a temporary folder and swapped in only when all are complete (``write_outputs``).

A DICOM series is placed by its headers: it cannot be re-oriented (``InputError``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from engine.defect.params import DEFECT_REORIENT
from engine.errors import InputError
from engine.export.files import MODEL_GLB, OPEN_STL, PRINT_STL, REPORT_JSON
from engine.params import OrientParams, ReconParams

if TYPE_CHECKING:
    from engine.device import DeviceSpec
    from engine.report import Report
    from engine.types import Volume

__all__ = ["current_orient", "read_report", "reorient", "stack_frame"]


def read_report(folder: str | Path) -> Report:
    """The output folder's ``report.json``.

    Raises:
        InputError: no report there (not a bonemesh output folder).
    """
    path = Path(folder) / REPORT_JSON
    if not path.is_file():
        raise InputError(f"{folder}: no {REPORT_JSON}; not a bonemesh output folder")
    return cast("Report", json.loads(path.read_text()))


def current_orient(report: Report) -> OrientParams:
    """The ``OrientParams`` the report's model was placed with."""
    given = (report.get("parameters") or {}).get("orient") or {}
    names = {f.name for f in dataclasses.fields(OrientParams)}
    return OrientParams(**{k: v for k, v in given.items() if k in names})


def _is_stack(report: Report) -> bool:
    placed_by = str((report.get("frame") or {}).get("placed_by", ""))
    return not placed_by.startswith("DICOM")


def stack_frame(report: Report, orient: OrientParams) -> Any:
    """The grid -> patient ``engine.orient.Frame`` that reconstructing the report's stack with ``orient`` gives
    (``engine.orient.patient_frame`` on the stack's shape, voxel size and origin, the origin recovered from the
    report's frame)."""
    from engine.orient import Frame, patient_frame

    shape = [int(n) for n in report["input"]["shape_zyx"]]
    spacing = [float(s) for s in report["input"]["spacing_zyx_mm"]]
    old = Frame.from_dict(report.get("frame"))
    extent_xyz = np.array([(n - 1) * s for n, s in zip(shape, spacing, strict=True)])[::-1]
    signs = np.diag(old.matrix)
    origin = np.where(signs < 0, extent_xyz - old.offset_mm, old.offset_mm)  # inverse of patient_frame's offset
    volume = SimpleNamespace(
        patient_frame=False, data=SimpleNamespace(shape=tuple(shape)), spacing_zyx_mm=spacing, origin_mm=origin
    )
    return patient_frame(cast("Volume", volume), orient)


def _grid_mesh(folder: Path, report: Report) -> Any:
    """The print model back in the grid frame (``engine.types.Mesh``: vertices (z, y, x) mm, the pipeline's faces
    and normals)."""
    from engine.export.glb import GLTF_FROM_XYZ, read_glb
    from engine.export.stl import _FACET
    from engine.orient import Frame
    from engine.types import Mesh

    stl = folder / PRINT_STL if (folder / PRINT_STL).is_file() else folder / OPEN_STL
    if not stl.is_file() or not (folder / MODEL_GLB).is_file():
        raise InputError(f"{folder}: the print model ({PRINT_STL} and {MODEL_GLB}) is missing")
    _, gltf_normals, tris = read_glb((folder / MODEL_GLB).read_bytes())
    data = stl.read_bytes()
    count = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if count != len(tris) or len(data) != 84 + count * _FACET.itemsize:
        raise InputError(f"{folder}: {stl.name} and {MODEL_GLB} do not hold the same model")
    corners = np.frombuffer(data, dtype=_FACET, count=count, offset=84)["v"].reshape(-1, 3, 3)
    patient = np.zeros((len(gltf_normals), 3), np.float64)
    patient[tris.astype(np.int64).ravel()] = corners.reshape(-1, 3)  # exact float32 positions, glTF's order
    frame = Frame.from_dict(report.get("frame"))
    grid_xyz = (patient - frame.offset_mm) @ frame.matrix  # matrix orthonormal: its inverse is its transpose
    normals_xyz = (gltf_normals.astype(np.float64) @ GLTF_FROM_XYZ) @ frame.matrix
    faces = tris.astype(np.int32)
    if frame.mirrored:  # the files' faces were reversed to stay outward: back to the pipeline's winding
        faces = faces[:, ::-1]
    return Mesh(
        np.ascontiguousarray(grid_xyz[:, ::-1], np.float32),
        np.ascontiguousarray(faces),
        np.ascontiguousarray(normals_xyz[:, ::-1], np.float32),
    )


def reorient(
    folder: str | Path,
    orient: OrientParams,
    *,
    device: DeviceSpec = "auto",
    max_device_bytes: Any = None,
    outdir: str | Path | None = None,
) -> dict[str, Path]:
    """Write a finished output folder's files again with the stack placed by ``orient`` (see the module docstring).

    Args:
        folder: the output folder of ``write_outputs`` (``bonemesh`` CLI, or a job's outputs).
        orient: the new orientation, absolute (as ``ReconParams.orient``): the same params give the same files, so
            repeating a call changes nothing.
        device, max_device_bytes: as ``write_outputs``.
        outdir: where to write (default: ``folder`` itself, every file replaced once all are written).

    Returns:
        The files written, by name (as ``write_outputs``).

    Raises:
        InputError: not an output folder, a label job's, its print model is missing, or the model is of a DICOM
            series.
    """
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import Reconstruction

    src = Path(folder)
    report = read_report(src)
    if report.get("labels") is not None:  # a label job (engine.labels): its map places every model
        raise InputError(
            f"{src}: a label job's models are placed by their label map (or are a CT's pieces): not re-oriented"
        )
    if not _is_stack(report):
        raise InputError(
            f"{src}: a DICOM series is placed in the patient by its headers; only an image stack can be re-oriented"
        )
    if (report.get("parameters") or {}).get("defect") is not None:
        raise InputError(DEFECT_REORIENT.format(job=str(src)))
    before = current_orient(report)
    mesh = _grid_mesh(src, report)
    params_dict = dict(report.get("parameters") or {})
    params_dict["orient"] = dataclasses.asdict(orient)
    params = ReconParams.from_dict(params_dict)
    new: dict[str, Any] = dict(report)
    new["parameters"] = params.to_dict()
    new["frame"] = stack_frame(report, orient).to_dict()
    for written in ("layout", "print_check", "exports", "write_seconds"):  # write_outputs writes them again
        new.pop(written, None)
    new["reoriented"] = {"from": dataclasses.asdict(before), "to": dataclasses.asdict(orient)}
    recon = Reconstruction(mesh=mesh, report=cast("Report", new))
    return write_outputs(recon, outdir or src, params, device=device, max_device_bytes=max_device_bytes)
