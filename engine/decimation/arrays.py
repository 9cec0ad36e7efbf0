"""The decimation's numpy entry point (``decimate_mesh``): arrays in, arrays and a full report out, by the device
kernels (``engine.decimation.passes``, Warp or OpenCL) or MeshLab's collapse (``engine.decimation.meshlab``, the
reference).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.decimation.passes import TOLERANCE, decimate_device
from engine.params import target_faces
from engine.surface.meshcheck import boundary_kept, component_labels, edge_report, folds, signed_volume, validate_mesh


def decimate_mesh(
    verts: npt.NDArray[Any],
    faces: npt.NDArray[Any],
    *,
    reduction: float | None = None,
    max_triangles: int | None = None,
    device: Any = "auto",
    method: str = "auto",
    workers: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32], dict[str, Any]]:
    """Reduce the face count by topology-preserving quadric-error edge collapses.

    Args:
        verts: (V, 3) vertices in (z, y, x) order, mm.
        faces: (F, 3) integer vertex indices, outward normals with vertices in (x, y, z) order.
        reduction: fraction of the faces to keep, in (0, 1] (0.2 keeps about 20 %).
        max_triangles: or the number of faces to reduce to (>= 1); at or above F the mesh is returned as is.
        device: the device (spec) of the device kernels: a Warp device, ``"auto"``, ``"cpu"``, ``"cuda[:N]"``, or
            ``"opencl[:N]"`` for their OpenCL twins (``engine.backend.get_backend``).
        method: ``"warp"`` (the device kernels, on ``device``'s backend), ``"meshlab"`` (MeshLab's collapse in CPU
            processes) or ``"auto"`` (the device kernels: the faster on every device measured, see
            ``docs/benchmarks.md``).
        workers: MeshLab processes (``method="meshlab"`` only).

    Returns:
        ``(verts, faces, info)``: float32 (z, y, x) vertices, int32 faces, and ``info`` with ``method``,
        ``target_faces``, ``input_faces``, ``output_faces``, ``achieved_ratio``, ``limited_by_watertightness``
        (closed input whose result keeps more than 5 % over the target), ``closed_input``, ``closed_output``,
        ``boundary_preserved``, ``folds_before`` / ``folds_after`` (edges whose faces turn by more than 90
        degrees), ``components_before``, ``components_after``, ``volume_change`` (relative), ``seconds``, and for
        the Warp path ``passes`` and ``stopped``.

    Raises:
        ValueError: bad arrays or arguments.
    """
    from engine.surface.islands import compact_mesh

    t0 = time.perf_counter()
    verts, faces = validate_mesh(verts, faces)
    if len(faces) == 0:
        raise ValueError("Cannot decimate an empty mesh")
    if not np.isfinite(verts).all():
        raise ValueError("Vertices must be finite")
    if method not in ("auto", "warp", "meshlab"):
        raise ValueError(f"method must be auto, warp or meshlab, got {method!r}")
    target = target_faces(len(faces), reduction, max_triangles)
    verts, faces = compact_mesh(verts, faces)
    pts = verts[:, ::-1].astype(np.float64)
    before = edge_report(faces, len(pts))
    closed = before["boundary_edges"] == 0 and before["nonmanifold_edges"] == 0
    info: dict[str, Any] = {
        "target_faces": target,
        "input_faces": len(faces),
        "closed_input": bool(closed),
        "components_before": component_labels(faces, len(pts))[0],
    }
    if target >= len(faces):
        out_v, out_faces = verts, faces
        info["method"] = "none (at or under the target)"
    elif method == "meshlab":
        from engine.decimation.meshlab import collapse_meshlab

        out_v, out_faces, extra = collapse_meshlab(pts, faces, target, closed, workers)
        info.update(extra)
    else:
        out_v, out_faces, extra = _collapse_device(verts, faces, target, device)
        info.update(extra)
    out_pts = out_v[:, ::-1].astype(np.float64)
    after = edge_report(out_faces, len(out_pts))
    closed_out = after["boundary_edges"] == 0 and after["nonmanifold_edges"] == 0
    vol_in = signed_volume(pts, faces)
    vol_out = signed_volume(out_pts, out_faces)
    info.update(
        output_faces=len(out_faces),
        achieved_ratio=len(out_faces) / len(faces),
        limited_by_watertightness=bool(closed and len(out_faces) > target * (1 + TOLERANCE)),
        closed_output=bool(closed_out),
        boundary_preserved=bool(before["boundary_edges"] == 0 or boundary_kept(pts, faces, out_pts)),
        folds_before=folds(pts, faces),
        folds_after=folds(out_pts, out_faces),
        components_after=component_labels(out_faces, len(out_pts))[0],
        volume_change=(vol_out - vol_in) / vol_in if vol_in else 0.0,
        seconds=time.perf_counter() - t0,
    )
    return np.ascontiguousarray(out_v, dtype=np.float32), out_faces, info


def _collapse_device(
    verts: npt.NDArray[Any], faces: npt.NDArray[Any], target: int, device: Any
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32], dict[str, Any]]:
    """The device kernels' decimation on the backend of ``device`` (Warp or OpenCL)."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.backend.select import get_backend

    be = get_backend(device)
    p, f, st = decimate_device(be.from_host(verts, VEC3F), be.from_host(faces, VEC3I), target)
    out_v, out_faces = be.to_host(p), be.to_host(f).astype(np.int32)  # sync point
    kind = "warp" if be.kind == "warp" else "opencl"
    device_name = str(be.device) if be.kind == "warp" else be.label  # type: ignore[attr-defined]
    extra = {"method": f"{kind} quadric edge collapse", "device": device_name, "passes": st.passes}
    return out_v, out_faces, extra | {"stopped": st.stopped, "vertex_classes": st.vertex_classes}
