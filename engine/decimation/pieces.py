"""Decimation of a flagged piece of a device mesh beside the rest of it (a seam across slab groups' borders, or
a z tile): the piece is split off, pinned where it meets the rest, decimated and joined back, all on the device
(the mesh's backend), where that fits the memory budget (``decimate_piece_device``); and the cost model it is
planned with (the mesh and its joined copy, 12 B per vertex and per face, beside ``Costs.piece`` per face of the
piece).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from engine.budget import Budget, Costs


def piece_base(n_verts: int, n_faces: int) -> tuple[int, int]:
    """What a seam pass over a mesh needs besides ``Costs.piece`` per seam face, and the least it needs:
    the mesh (its callers hold it) and its joined copy; at least the mesh three times over (the joined copy and
    the compacted result; measured on the CPU: up to 1.46x the first term alone, small seams)."""
    mesh = (n_faces + n_verts) * 12
    return mesh + n_faces * 12, 3 * mesh


def piece_need(n_verts: int, n_faces: int, n_seam: int, costs: Costs) -> int:
    """Device bytes of a seam pass over ``n_seam`` of a mesh's faces: the seam split off and decimated beside the
    mesh, then joined back (``piece_base``)."""
    base, least = piece_base(n_verts, n_faces)
    return max(base + n_seam * costs.piece, least)


def piece_room(n_verts: int, n_faces: int, budget: Budget) -> int:
    """The most faces a tile of a device mesh may have for its pass beside the mesh (``piece_need`` within a
    limited ``budget``), 0 if none."""
    base, least = piece_base(n_verts, n_faces)
    room = budget.share(1)
    return 0 if least > room else max((room - base) // budget.costs.piece, 0)


def decimate_piece_device(
    pos: Any, faces: Any, flags: Any, goal_of: Any, budget: Budget, **options: Any
) -> tuple[tuple[Any, Any] | None, dict[str, Any]]:
    """Decimate the faces that ``flags(flag)`` flags (1 in an int32 per face: a seam or a z tile) on the device
    beside the rest of the mesh, where that fits ``budget``: split off, pinned where they meet the rest, decimated
    to ``goal_of(flagged faces)`` (quadrics from the current faces; ``options`` for ``decimate_carrying``) and
    joined back. ``((pos, faces), info)``, or
    ``(None, why)`` where it does not fit. The caller's ``pos`` and ``faces`` may be freed once it returns."""
    from engine.backend.base import VEC3F, VEC3I
    from engine.backend.select import backend_of
    from engine.decimation import kernel_specs as K
    from engine.decimation.passes import decimate_carrying
    from engine.surface import devmesh

    t0 = time.perf_counter()
    be = backend_of(pos)
    n_faces, n_verts = len(faces), len(pos)
    flag, slot = be.empty(n_faces, np.int32), be.empty(n_faces, np.int32)
    flags(flag)
    n_seam = be.exclusive_scan(flag, slot)  # sync point
    need = piece_need(n_verts, n_faces, n_seam, budget.costs)
    if n_seam == 0 or not budget.fits(need):
        return None, {"seam_faces": n_seam, "faces": n_faces, "need_bytes": need, "budget_bytes": budget.bytes}
    in_seam, in_rest = be.zeros(n_verts, np.int32), be.zeros(n_verts, np.int32)
    be.launch(K.MARK_USED, n_faces, [faces, flag, 1, in_seam])
    be.launch(K.MARK_USED, n_faces, [faces, flag, 0, in_rest])
    vslot = be.empty(n_verts, np.int32)
    n_local = be.exclusive_scan(in_seam, vslot)  # sync point
    seam, rest = be.empty(n_seam, VEC3I), be.empty(n_faces - n_seam, VEC3I)
    be.launch(K.SPLIT_FACES, n_faces, [faces, flag, slot, vslot, seam, rest])
    del flag, slot
    vids, local_pos, lock = be.empty(n_local, np.int32), be.empty(n_local, VEC3F), be.empty(n_local, np.int32)
    be.launch(K.GATHER_SEAM, n_verts, [pos, in_seam, in_rest, vslot, vids, local_pos, lock])
    del in_seam, in_rest, vslot
    res = decimate_carrying(local_pos, seam, goal_of(n_seam), locked=lock, **options)
    del local_pos, seam
    n_out = len(res.pos)
    new, new_slot = be.empty(n_out, np.int32), be.empty(n_out, np.int32)
    be.launch(K.NEW_VERTEX_FLAGS, n_out, [res.kept, lock, new])
    n_new = be.exclusive_scan(new, new_slot)  # sync point
    out_id = be.empty(n_out, np.int32)
    joined_pos = be.empty(n_verts + n_new, VEC3F)
    be.copy(joined_pos, pos, count=n_verts)
    new_pos = be.empty(max(n_new, 1), VEC3F)
    be.launch(K.JOIN_SEAM, n_out, [res.pos, res.kept, lock, vids, new_slot, n_verts, out_id, new_pos])
    if n_new:
        be.copy(joined_pos, new_pos, dst_offset=n_verts, count=n_new)
    be.launch(K.REMAP_FACES, len(res.faces), [res.faces, out_id])
    joined = be.empty(len(rest) + len(res.faces), VEC3I)
    be.copy(joined, rest, count=len(rest))
    be.copy(joined, res.faces, dst_offset=len(rest), count=len(res.faces))
    del rest, pos, faces
    out_pos, out_faces = devmesh.compact_vertices(joined_pos, joined)  # drops the seam's replaced vertices
    pinned = res.stats.vertex_classes.get("locked")
    info = {"faces_in": n_faces, "seam_faces_in": n_seam, "seam_faces_out": len(res.faces), "pinned": pinned}
    info.update(faces_out=len(out_faces), passes=res.stats.passes, seconds=time.perf_counter() - t0, on="device")
    return (out_pos, out_faces), info
