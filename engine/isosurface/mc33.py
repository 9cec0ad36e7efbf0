"""Marching Cubes 33 host wrapper: validate, then per z slab: classify blocks -> count -> scan -> emit.

Topology follows the trilinear interpolant (see ``engine.isosurface._make_mc33_tables``). The volume is processed
in slabs of whole block layers along z with a one-plane overlap; vertex ids continue across slabs (the ids of the
slab's first plane come from the previous slab), so the result is identical to a single pass.

Ties: a sample equal to the level counts as above it (the "at or above" rule of a bone threshold), and an edge
point is never placed closer than ``TIE_TAU`` (in units of the edge) to a sample. Integer data at an integer
level therefore gives the same topology as a level lowered by an infinitesimal amount, without coincident
vertices or zero-area faces.

Closed surfaces: samples outside the array are infinitely far below the level (the limit of padding with ever
lower values, so the result does not depend on a pad value or on the data's offset and scale): faces touching
them are never ambiguous, cells touching them have no interior joins, and the vertex on an edge leaving the
array sits half a voxel outside it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from engine.backend.base import VEC3F, VEC3I, Backend
from engine.isosurface.slabs import SlabPlan, join_parts, run_slabs
from engine.isosurface.stats import IsosurfaceStats, Timer

__all__ = ["extract_isosurface", "marching_cubes_33"]
SUPPORTED_DTYPES = (np.uint8, np.uint16, np.int16, np.float32)


def _validate(volume: Any, level: float, spacing: Any) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    if not isinstance(volume, np.ndarray):
        raise ValueError(f"Expected a 3-D numpy array, got {type(volume).__name__}")
    if volume.ndim != 3:
        raise ValueError(f"Expected a 3-D volume (nz, ny, nx), got {volume.ndim} dimensions with shape {volume.shape}")
    if min(volume.shape) < 2:
        raise ValueError(f"Expected every dimension of the volume to be at least 2, got shape {volume.shape}")
    if volume.dtype.type not in SUPPORTED_DTYPES:
        names = ", ".join(np.dtype(t).name for t in SUPPORTED_DTYPES)
        raise ValueError(f"Expected a volume of dtype {names}, got {volume.dtype}")
    try:
        lvl = float(level)
    except (TypeError, ValueError):
        raise ValueError(f"Expected a real iso level, got {level!r}") from None
    if not np.isfinite(lvl):
        raise ValueError(f"Expected a finite iso level, got {level!r}")
    try:
        sp = tuple(float(s) for s in spacing)
    except (TypeError, ValueError):
        raise ValueError(f"Expected spacing as 3 positive numbers (z, y, x) in mm, got {spacing!r}") from None
    if len(sp) != 3 or not all(np.isfinite(s) and s > 0 for s in sp):
        raise ValueError(f"Expected spacing as 3 positive numbers (z, y, x) in mm, got {spacing!r}")
    return np.ascontiguousarray(volume), float(np.float32(lvl)), (sp[0], sp[1], sp[2])


def _budget(max_device_bytes: int | None, be: Backend) -> int:
    budget = int(max_device_bytes) if max_device_bytes is not None else be.default_budget()
    if budget <= 0:
        raise ValueError(f"Expected a positive max_device_bytes, got {max_device_bytes!r}")
    return budget


def marching_cubes_33(
    volume: npt.NDArray[Any],
    level: float,
    *,
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0),
    device: Any = "auto",
    closed: bool = False,
    max_device_bytes: int | None = None,
    stats: IsosurfaceStats | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Extract the isosurface of the trilinear interpolant of ``volume`` at ``level`` (Marching Cubes 33).

    Args:
        volume: (nz, ny, nx) array of uint8, uint16, int16 or float32; converted to float on the device.
        level: iso value in the volume's units. Samples equal to it count as above it.
        spacing: voxel size (z, y, x) in mm; vertices are scaled by it.
        device: "auto", "cpu", "cuda" or "cuda:N" (Warp), "opencl" or "opencl:N" (OpenCL), or a backend
            (``engine.backend.get_backend``). Every backend gives the same mesh.
        closed: treat everything outside the array as below the level, so the surface is watertight.
        max_device_bytes: working-set budget per slab; default half the free device memory (a quarter of
            the available RAM on the CPU). The volume is uploaded slab by slab.
        stats: optional object filled with what the run did.

    Returns:
        ``verts`` (V, 3) float32 in (z, y, x) order scaled by ``spacing``, and ``faces`` (F, 3) int32, oriented so
        that with ``verts[:, ::-1]`` normals point from values above ``level`` toward values below it.
        A level outside the data range gives an empty mesh.

    Raises:
        ValueError: the volume, level, spacing or device is not as expected, or a float volume holds NaN.
    """
    vol, lvl, sp = _validate(volume, level, spacing)
    from engine.backend.select import get_backend

    be = get_backend(device)
    st = stats if stats is not None else IsosurfaceStats()
    budget = _budget(max_device_bytes, be)
    vert_parts: list[np.ndarray] = []
    face_parts: list[np.ndarray] = []

    def upload(zlo: int, zhi: int) -> Any:
        return be.from_host(vol[zlo : zhi + 1])

    plan = SlabPlan(budget, vol.shape[1] * vol.shape[2] * vol.itemsize)
    for part in run_slabs(upload, vol.shape, plan, vol.dtype == np.float32, lvl, sp, closed, be, st):
        timer = Timer(st, be)
        vert_parts.append(be.to_host(part.verts, part.nv))  # sync point
        face_parts.append(be.to_host(part.faces, part.nt))  # sync point
        timer.lap("download")
    if not st.level_in_range or not face_parts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    verts_np = np.concatenate(vert_parts).astype(np.float32, copy=False).reshape(-1, 3)
    faces_np = np.concatenate(face_parts).astype(np.int32, copy=False).reshape(-1, 3)
    return verts_np, faces_np


def _device_field(field: Any) -> tuple[Backend, np.dtype[Any]]:
    """The backend and sample type of a device volume (a Warp array or an OpenCL ``CLArray``), checked."""
    from engine.backend.select import backend_of
    from engine.volume.gaussian import sample_dtype

    ok = False
    if type(field).__name__ == "CLArray":
        ok = field.ndim == 3 and np.dtype(field.dtype).type in SUPPORTED_DTYPES
    else:
        import warp as wp

        ok = (
            isinstance(field, wp.array)
            and field.ndim == 3
            and field.dtype in (wp.uint8, wp.uint16, wp.int16, wp.float32)
        )
    if not ok:
        got = f"{type(field).__name__} ndim={getattr(field, 'ndim', None)} dtype={getattr(field, 'dtype', None)}"
        raise ValueError(f"Expected a 3-D Warp array (or an OpenCL one) of uint8, uint16, int16 or float32, got {got}")
    if min(field.shape) < 2:
        raise ValueError(f"Expected every dimension of the volume to be at least 2, got shape {field.shape}")
    return backend_of(field), sample_dtype(field)


def extract_isosurface(
    field: Any,
    level: float,
    *,
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0),
    closed: bool = False,
    max_device_bytes: int | None = None,
    stats: IsosurfaceStats | None = None,
) -> tuple[Any, Any]:
    """Device-resident Marching Cubes 33: a device volume in, device arrays out, on the field's backend.

    Args:
        field: (nz, ny, nx) device volume of uint8, uint16, int16 or float32: a ``wp.array3d`` (Warp) or an
            ``engine.backend`` OpenCL array.
        level, spacing, closed, max_device_bytes, stats: as for :func:`marching_cubes_33` (the budget bounds the
            per-slab working set; the field itself is already resident).

    Returns:
        ``verts`` (z, y, x) in mm and ``faces``: ``wp.array(dtype=wp.vec3)`` and ``wp.array(dtype=wp.vec3i)`` on
        Warp, arrays of ``VEC3F`` / ``VEC3I`` on OpenCL (``engine.backend``).

    Raises:
        ValueError: as for :func:`marching_cubes_33`.
    """
    be, dtype = _device_field(field)
    probe = np.zeros((2, 2, 2), dtype)
    _, lvl, sp = _validate(probe, level, spacing)
    st = stats if stats is not None else IsosurfaceStats()
    budget = _budget(max_device_bytes, be)

    def view(zlo: int, zhi: int) -> Any:
        return be.view(field, zlo, zhi + 1)

    plan = SlabPlan(budget, field.shape[1] * field.shape[2] * dtype.itemsize)
    parts = list(run_slabs(view, tuple(field.shape), plan, dtype == np.float32, lvl, sp, closed, be, st))
    if not st.level_in_range or not parts:
        return be.empty(0, VEC3F), be.empty(0, VEC3I)
    return join_parts(parts, be)
