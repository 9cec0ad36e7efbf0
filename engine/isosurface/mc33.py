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

import os
from typing import Any

import numpy as np
import numpy.typing as npt

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


def _default_budget(dev: Any) -> int:
    if dev.is_cuda:
        return int(dev.free_memory * 0.5)
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        avail = 8 << 30
    return int(avail * 0.25)


def _budget(max_device_bytes: int | None, dev: Any) -> int:
    budget = int(max_device_bytes) if max_device_bytes is not None else _default_budget(dev)
    if budget <= 0:
        raise ValueError(f"Expected a positive max_device_bytes, got {max_device_bytes!r}")
    return budget


def marching_cubes_33(
    volume: npt.NDArray[Any],
    level: float,
    *,
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0),
    device: str = "auto",
    closed: bool = False,
    max_device_bytes: int | None = None,
    stats: IsosurfaceStats | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Extract the isosurface of the trilinear interpolant of ``volume`` at ``level`` (Marching Cubes 33).

    Args:
        volume: (nz, ny, nx) array of uint8, uint16, int16 or float32; converted to float on the device.
        level: iso value in the volume's units. Samples equal to it count as above it.
        spacing: voxel size (z, y, x) in mm; vertices are scaled by it.
        device: "auto", "cpu", "cuda" or "cuda:N".
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
    from engine.device import resolve_device

    dev = resolve_device(device)
    import warp as wp

    st = stats if stats is not None else IsosurfaceStats()
    budget = _budget(max_device_bytes, dev)
    vert_parts: list[np.ndarray] = []
    face_parts: list[np.ndarray] = []
    with wp.ScopedDevice(dev):

        def upload(zlo: int, zhi: int) -> Any:
            return wp.array(vol[zlo : zhi + 1], device=dev)

        plan = SlabPlan(budget, vol.shape[1] * vol.shape[2] * vol.itemsize)
        for part in run_slabs(upload, vol.shape, plan, vol.dtype == np.float32, lvl, sp, closed, dev, st):
            timer = Timer(st, dev)
            vert_parts.append(part.verts.numpy()[: part.nv])  # sync point
            face_parts.append(part.faces.numpy()[: part.nt])  # sync point
            timer.lap("download")
    if not st.level_in_range or not face_parts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    verts_np = np.concatenate(vert_parts).astype(np.float32, copy=False).reshape(-1, 3)
    faces_np = np.concatenate(face_parts).astype(np.int32, copy=False).reshape(-1, 3)
    return verts_np, faces_np


def extract_isosurface(
    field: Any,
    level: float,
    *,
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0),
    closed: bool = False,
    max_device_bytes: int | None = None,
    stats: IsosurfaceStats | None = None,
) -> tuple[Any, Any]:
    """Device-resident Marching Cubes 33: a Warp array in, Warp arrays out, on the field's device.

    Args:
        field: ``wp.array3d`` (nz, ny, nx) of uint8, uint16, int16 or float32.
        level, spacing, closed, max_device_bytes, stats: as for :func:`marching_cubes_33` (the budget bounds the
            per-slab working set; the field itself is already resident).

    Returns:
        ``verts`` ``wp.array(dtype=wp.vec3)`` (z, y, x) in mm and ``faces`` ``wp.array(dtype=wp.vec3i)``.

    Raises:
        ValueError: as for :func:`marching_cubes_33`.
    """
    import warp as wp

    kinds = {wp.uint8: np.uint8, wp.uint16: np.uint16, wp.int16: np.int16, wp.float32: np.float32}
    if not isinstance(field, wp.array) or field.ndim != 3 or field.dtype not in kinds:
        got = f"{type(field).__name__} ndim={getattr(field, 'ndim', None)} dtype={getattr(field, 'dtype', None)}"
        raise ValueError(f"Expected a 3-D Warp array of uint8, uint16, int16 or float32, got {got}")
    if min(field.shape) < 2:
        raise ValueError(f"Expected every dimension of the volume to be at least 2, got shape {field.shape}")
    probe = np.zeros((2, 2, 2), kinds[field.dtype])
    _, lvl, sp = _validate(probe, level, spacing)
    dev = field.device
    st = stats if stats is not None else IsosurfaceStats()
    budget = _budget(max_device_bytes, dev)
    itemsize = np.dtype(kinds[field.dtype]).itemsize
    with wp.ScopedDevice(dev):

        def view(zlo: int, zhi: int) -> Any:
            return field[zlo : zhi + 1]

        plan = SlabPlan(budget, field.shape[1] * field.shape[2] * itemsize)
        parts = list(run_slabs(view, field.shape, plan, field.dtype == wp.float32, lvl, sp, closed, dev, st))
        if not st.level_in_range or not parts:
            return wp.empty(0, dtype=wp.vec3), wp.empty(0, dtype=wp.vec3i)
        return join_parts(parts)
