"""The last decimation across the borders of slab groups (the seams): only the faces near a border are decimated
again, pinned where they meet the rest; on the device beside the mesh where that fits the budget (all the seams
at once, or in batches of neighbouring borders), else on the host (``seam_pass``, tiles on the device).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from engine.budget import Budget
from engine.decimation.pieces import decimate_piece_device, piece_need
from engine.decimation.tiles import HostMesh, decimate_tiles

SEAM_MAX_PASSES = 60  # the seams' goal may be out of the guards' reach: passes past this win little


def seam_pass(
    mesh: HostMesh, borders_z: list[float], width_mm: float, target: int, budget: Budget, dev: Any, **kwargs: Any
) -> tuple[HostMesh, dict[str, Any]]:
    """Decimate across the borders of the slab groups: the faces within ``width_mm`` of a border (in z) form one
    tile, pinned where they meet the rest, which is left as it is; the tile gives up the faces over ``target``.
    A tile that does not fit ``budget`` is left to the tiled rounds (``info["skipped"]``)."""
    z = mesh.pos[mesh.faces[:, 0], 0]
    b = np.sort(np.asarray(borders_z, np.float64))
    i = np.clip(np.searchsorted(b, z), 1, len(b) - 1) if len(b) > 1 else np.zeros(len(z), np.int64)
    near = np.minimum(np.abs(z - b[i]), np.abs(z - b[np.maximum(i - 1, 0)])) <= width_mm
    tile = np.where(near, 0, 1).astype(np.int16)
    n_seam = int(near.sum())
    if not budget.fits_decimation(n_seam):
        return mesh, {"skipped": {"seam_faces": n_seam, "budget_bytes": budget.bytes}}
    goal = max(n_seam - (len(mesh.faces) - target), 1)
    return decimate_tiles(mesh, tile, {0: goal}, dev, **kwargs)


def seams_fit_beside(n_verts: int, n_faces: int, budget: Budget) -> bool:
    """Whether a mesh this size leaves room within ``budget`` for a device seam pass (of at least one small seam);
    ``Budget.seams_beside`` where set."""
    if budget.seams_beside is not None:
        return budget.seams_beside
    return budget.fits(piece_need(n_verts, n_faces, 0, budget.costs))


def seam_pass_device(
    pos: Any,
    faces: Any,
    borders_z: list[float],
    width_mm: float,
    target: int,
    budget: Budget,
    keep: float | None = None,
) -> tuple[tuple[Any, Any] | None, dict[str, Any]]:
    """``seam_pass`` on a device mesh, where the seam's decimation fits ``budget`` beside the mesh: the seam's faces
    are decimated (quadrics from the current faces), pinned where they meet the rest, down to the mesh's ``target``
    (or to ``keep`` of the seam's faces). ``((pos, faces), info)``, or ``(None, why)`` where it does not fit (or
    where it would take more borders than ``Budget.seam_batch_borders``)."""
    from engine.backend.select import backend_of
    from engine.decimation import kernel_specs as K

    be = backend_of(pos)
    n_faces = len(faces)

    def flags(flag: Any) -> None:
        borders = be.from_host(np.asarray(borders_z, np.float32))
        be.launch(K.SEAM_FLAGS, n_faces, [pos, faces, borders, len(borders_z), float(width_mm), flag])

    def goal(n_seam: int) -> int:
        return max(n_seam - (n_faces - target) if keep is None else round(keep * n_seam), 1)

    if budget.seam_batch_borders is not None and len(borders_z) > budget.seam_batch_borders:
        budget = budget.with_bytes(1)  # as if they did not fit together
    return decimate_piece_device(pos, faces, flags, goal, budget, max_passes=SEAM_MAX_PASSES)


def seam_passes_device(
    mesh: list[Any], borders_z: list[float], width_mm: float, target: int, budget: Budget
) -> tuple[tuple[Any, Any], dict[str, Any]]:
    """``seam_pass`` on a device mesh (``mesh``: ``[pos, faces]``, emptied: each batch's input is freed once
    replaced), within ``budget``: all the seams at once where they fit beside the mesh, else in batches of
    neighbouring borders (halved until each fits), every seam giving up the same share of its faces.
    ``((pos, faces), info)``; ``info["complete"]`` is False where even one border's seam would not fit (the mesh
    then holds the batches done so far, ``info["skipped"]`` says why and ``info["remaining"]`` lists the borders
    not done)."""
    t0 = time.perf_counter()
    pos, faces = mesh
    mesh.clear()
    n_faces = len(faces)
    done, why = seam_pass_device(pos, faces, borders_z, width_mm, target, budget)
    if done is not None:
        return done, {**why, "batches": 1, "complete": True}
    n_seam = why["seam_faces"]
    info: dict[str, Any] = {"faces_in": n_faces, "seam_faces_in": n_seam, "on": "device", "passes": []}
    info.update(batches=0, complete=False, skipped=why, remaining=sorted(borders_z))
    if n_seam == 0 or len(borders_z) < 2:
        return (pos, faces), info
    keep = max(1.0 - (n_faces - target) / n_seam, 0.0)
    queue = [sorted(borders_z)]
    while queue:
        batch = queue.pop(0)
        done, why = seam_pass_device(pos, faces, batch, width_mm, target, budget, keep=keep)
        if done is None:
            if len(batch) < 2 or why["seam_faces"] == 0:
                info["skipped"], info["remaining"] = why, sorted(b for part in [batch, *queue] for b in part)
                break
            half = len(batch) // 2
            queue[:0] = [batch[:half], batch[half:]]
            continue
        (pos, faces), info["batches"] = done, info["batches"] + 1
        info["passes"].append(why["passes"])
    else:
        info["complete"] = True
        del info["skipped"], info["remaining"]
    info.update(faces_out=len(faces), seconds=time.perf_counter() - t0)
    return (pos, faces), info
