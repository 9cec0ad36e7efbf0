"""Marching Cubes 33 host wrapper: validate, then per z slab: classify blocks -> count -> scan -> emit.

Topology follows the trilinear interpolant (see ``engine.kernels._make_mc33_tables``). The volume is processed
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

import functools
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

SUPPORTED_DTYPES = (np.uint8, np.uint16, np.int16, np.float32)
TIE_TAU = 1.0 / 1024.0
_INT32_MAX = 2**31 - 1


@dataclass
class IsosurfaceStats:
    """What a run did: slabs, active blocks, table misses (must be 0)."""

    slabs: int = 0
    blocks: int = 0
    active_blocks: int = 0
    table_misses: int = 0
    peak_slab_bytes: int = 0
    slab_layers: list[int] = field(default_factory=list)


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


@functools.cache
def _tables(device_name: str) -> dict[str, Any]:
    """Lookup tables uploaded once per device."""
    import warp as wp

    from engine.kernels import _make_mc33_tables as gen
    from engine.kernels import mc33_tables as t

    key_map = np.full(t.N_KEYS_DENSE, -1, dtype=np.int32)
    key_map[np.asarray(t.KEYS, dtype=np.int64)] = np.asarray(t.TRI_ID, dtype=np.int32)
    face_cyc = np.asarray([c for cyc, _ in gen.FACES for c in cyc], dtype=np.int32)

    def up(values: Any, dtype: Any) -> Any:
        return wp.array(np.asarray(values, dtype=dtype), dtype=wp.int32 if dtype == np.int32 else wp.float32,
                        device=device_name)

    return {
        "key_map": up(key_map, np.int32),
        "face_cyc": up(face_cyc, np.int32),
        "tri_offset": up(t.TRI_OFFSET, np.int32),
        "tri_count": up(t.TRI_COUNT, np.int32),
        "tri_local": up(t.TRIANGLES, np.int32),
        "ivert_offset": up(t.IVERT_OFFSET, np.int32),
        "ivert_count": up(t.IVERT_COUNT, np.int32),
        "ivert_weights": up(t.IVERT_WEIGHTS, np.float32),
    }


def _default_budget(dev: Any) -> int:
    if dev.is_cuda:
        return int(dev.free_memory * 0.5)
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        avail = 8 << 30
    return int(avail * 0.25)


def _layers_per_slab(shape: tuple[int, int, int], itemsize: int, budget: int) -> int:
    from engine.kernels.mc33 import BLOCK, BLOCK_CELLS

    nz, ny, nx = shape
    nby, nbx = -(-(ny + 1) // BLOCK), -(-(nx + 1) // BLOCK)
    # per block layer: the volume planes, and the worst case of every block active: 5 int32 per cell slot,
    # plus room for ~1 vertex and ~2 triangles per cell of output
    per_layer = BLOCK * ny * nx * itemsize + nby * nbx * (BLOCK_CELLS * (20 + 36) + 16)
    layers = max(1, budget // per_layer)
    layers = min(layers, max(1, (_INT32_MAX // 2) // (nby * nbx * BLOCK_CELLS)))
    return int(layers)


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
            the available RAM on the CPU).
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

    from engine.kernels import mc33 as k

    st = stats if stats is not None else IsosurfaceStats()
    tables = _tables(str(dev))
    nz, ny, nx = vol.shape
    budget = int(max_device_bytes) if max_device_bytes is not None else _default_budget(dev)
    if budget <= 0:
        raise ValueError(f"Expected a positive max_device_bytes, got {max_device_bytes!r}")
    layers = _layers_per_slab(vol.shape, vol.itemsize, budget)

    B = k.BLOCK
    nbz_total = -(-(nz + 1) // B)
    nby, nbx = -(-(ny + 1) // B), -(-(nx + 1) // B)
    flags = wp.zeros(4, dtype=wp.int32, device=dev)
    plane_prev = wp.full((2, ny + 1, nx + 1), -1, dtype=wp.int32, device=dev)
    vert_parts: list[np.ndarray] = []
    face_parts: list[np.ndarray] = []
    vstart = 0

    with wp.ScopedDevice(dev):
        for bz0 in range(0, nbz_total, layers):
            bz1 = min(bz0 + layers, nbz_total)
            cz_first = bz0 * B - 1
            cz_last = min(bz1 * B - 1, nz) - 1  # last cell layer (origin)
            zlo, zhi = max(cz_first, 0), min(cz_last + 1, nz - 1)
            sub = wp.array(vol[zlo : zhi + 1], device=dev)
            g = k.Grid()
            g.nz, g.ny, g.nx = nz, ny, nx
            g.zoff, g.bz0, g.nbz, g.nby, g.nbx = zlo, bz0, bz1 - bz0, nby, nbx
            g.cz_first = cz_first
            g.level = lvl
            g.pad = -1.0  # only its sign is used (see the module docstring)
            g.closed = int(bool(closed))
            g.tau = TIE_TAU
            g.sz, g.sy, g.sx = sp
            nblocks = g.nbz * nby * nbx
            if vol.dtype == np.float32:
                wp.launch(k.nan_kernel, dim=sub.shape, inputs=[sub, flags])
            active = wp.empty(nblocks, dtype=wp.int32)
            wp.launch(k.block_kernel, dim=nblocks, inputs=[sub, g, active, flags])
            bpos = wp.empty(nblocks, dtype=wp.int32)
            wp.utils.array_scan(active, bpos, inclusive=False)
            n_active = int(bpos[nblocks - 1 : nblocks].numpy()[0] + active[nblocks - 1 : nblocks].numpy()[0])  # sync
            alist = wp.empty(max(n_active, 1), dtype=wp.int32)
            bmap = wp.empty(nblocks, dtype=wp.int32)
            wp.launch(k.compact_blocks_kernel, dim=nblocks, inputs=[active, bpos, alist, bmap])
            st.slabs += 1
            st.blocks += nblocks
            st.active_blocks += n_active
            st.slab_layers.append(cz_last - cz_first + 1)
            nslots = n_active * k.BLOCK_CELLS
            slab_bytes = sub.capacity + nblocks * 12 + nslots * 20
            if nslots == 0:
                plane_prev.fill_(-1)
                st.peak_slab_bytes = max(st.peak_slab_bytes, slab_bytes)
                continue
            vcount = wp.empty(nslots, dtype=wp.int32)
            tcount = wp.empty(nslots, dtype=wp.int32)
            tri_id = wp.empty(nslots, dtype=wp.int32)
            wp.launch(
                k.count_kernel,
                dim=nslots,
                inputs=[sub, g, alist, tables["face_cyc"], tables["key_map"], tables["tri_count"],
                        tables["ivert_count"], vcount, tcount, tri_id, flags],
            )
            voff = wp.empty(nslots, dtype=wp.int32)
            toff = wp.empty(nslots, dtype=wp.int32)
            wp.utils.array_scan(vcount, voff, inclusive=False)
            wp.utils.array_scan(tcount, toff, inclusive=False)
            nv = int(voff[nslots - 1 : nslots].numpy()[0] + vcount[nslots - 1 : nslots].numpy()[0])  # sync point
            nt = int(toff[nslots - 1 : nslots].numpy()[0] + tcount[nslots - 1 : nslots].numpy()[0])  # sync point
            if vstart + nv > _INT32_MAX:
                raise ValueError(f"Expected at most {_INT32_MAX} vertices (int32 faces), got more than {vstart + nv}")
            verts = wp.empty(max(nv, 1), dtype=wp.vec3)
            faces = wp.empty(max(nt, 1), dtype=wp.vec3i)
            wp.launch(
                k.emit_kernel,
                dim=nslots,
                inputs=[sub, g, alist, bmap, vcount, voff, toff, tri_id, plane_prev, vstart,
                        tables["tri_offset"], tables["tri_count"], tables["tri_local"], tables["ivert_offset"],
                        tables["ivert_count"], tables["ivert_weights"], verts, faces],
            )
            plane_next = wp.empty((2, ny + 1, nx + 1), dtype=wp.int32)
            wp.launch(k.plane_kernel, dim=(ny + 1, nx + 1), inputs=[sub, g, bmap, voff, vstart, cz_last, plane_next])
            plane_prev = plane_next
            st.peak_slab_bytes = max(st.peak_slab_bytes, slab_bytes + nslots * 8 + nv * 12 + nt * 12)
            if nv:
                vert_parts.append(verts.numpy()[:nv])  # sync point
            if nt:
                face_parts.append(faces.numpy()[:nt])  # sync point
            vstart += nv
        fl = flags.numpy()  # sync point

    if fl[2]:
        raise ValueError("Expected a volume without NaN, got NaN values in the float volume")
    st.table_misses = int(fl[3])
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    if not (fl[0] and fl[1]) or not face_parts:
        return empty
    verts_np = np.concatenate(vert_parts).astype(np.float32, copy=False).reshape(-1, 3)
    faces_np = np.concatenate(face_parts).astype(np.int32, copy=False).reshape(-1, 3)
    return verts_np, faces_np
