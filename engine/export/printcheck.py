"""The check a print model must pass before it is written: watertight, 2-manifold (edges and vertices),
consistently oriented, enclosing a positive volume, without degenerate faces (repeated vertex or zero area).

The mesh diagnostics are :func:`engine.surface.meshcheck.mesh_stats` (the report's ``mesh`` block, reused when
given); this module only judges them. An open surface (``IsoParams.closed=False``) is not a print model: it is
written under another name (:data:`OPEN_STL`) and not checked.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from engine.errors import PrintCheckError  # also imported from here by worker.tasks
from engine.export.files import OPEN_STL, PRINT_STL  # the names are the registry's
from engine.params import ReconParams

if TYPE_CHECKING:
    from engine.report import PrintCheck

__all__ = ["OPEN_STL", "PRINT_STL", "PrintCheckError", "check_print_model", "stl_name", "zero_area_faces"]

_CHUNK = 1 << 21


def stl_name(params: ReconParams) -> str:
    """The STL's file name: the checked print model, or the explicitly open surface."""
    return PRINT_STL if params.iso.closed else OPEN_STL


def zero_area_faces(vertices: npt.NDArray[Any], faces: npt.NDArray[Any]) -> int:
    """Faces whose three corners are collinear or coincide (exactly zero area in float64), counted in chunks."""
    from engine.surface import face_normals

    count = 0
    for lo in range(0, len(faces), _CHUNK):
        n = face_normals(vertices, faces[lo : lo + _CHUNK])
        count += int(np.count_nonzero(~np.any(n, axis=1)))
    return count


def check_print_model(
    vertices: npt.NDArray[Any] | None,
    faces: npt.NDArray[Any] | None,
    stats: Mapping[str, Any] | None = None,
    zero_area: int | None = None,
) -> PrintCheck:
    """Judge a print model; returns the passed checks for the report.

    Args:
        vertices: (V, 3) in (z, y, x) order, mm.
        faces: (F, 3) integer indices, outward with vertices taken in (x, y, z) order.
        stats: ``mesh_stats(vertices, faces)`` when already computed (the pipeline report's ``mesh``).
        zero_area: ``zero_area_faces(vertices, faces)`` when already counted (on the device); with ``stats``
            given too, ``vertices`` and ``faces`` are not read.

    Raises:
        PrintCheckError: naming every check that failed, with its counts.
    """
    from engine.surface import mesh_stats

    st = stats if stats is not None else mesh_stats(vertices, faces)
    if zero_area is None:
        zero_area = zero_area_faces(vertices, faces)
    checks = {
        "watertight": (st["watertight"], f"{st['boundary_edges']} boundary edge(s), the mesh is open"),
        "two_manifold": (
            st["nonmanifold_edges"] == 0 and st["vertex_manifold"] is not False,
            f"{st['nonmanifold_edges']} edge(s) in more than two faces"
            + (", and vertices where several fans of faces meet" if st["vertex_manifold"] is False else ""),
        ),
        "consistently_oriented": (st["inconsistent_edges"] == 0, f"{st['inconsistent_edges']} edge(s) wound twice"),
        "positive_volume": (st["volume_mm3"] > 0, f"signed volume {st['volume_mm3']:.6g} mm³ (inside out or empty)"),
        "no_degenerate_faces": (
            st["degenerate_faces"] == 0 and zero_area == 0,
            f"{st['degenerate_faces']} face(s) with a repeated vertex, {zero_area} with zero area",
        ),
    }
    failed = [f"{name}: {why}" for name, (ok, why) in checks.items() if not ok]
    if failed:
        raise PrintCheckError(f"{PRINT_STL} failed the print check ({'; '.join(failed)})")
    return {"passed": True, "checks": sorted(checks), "faces": int(st["n_faces"])}
