"""Stage: decimation of a mesh too large for the device memory budget, tile by tile with pinned tile borders.

``decimate_within`` decimates a device mesh in one piece where its decimation fits the budget, as
``decimate_device`` does. Otherwise, where tiles fit beside the whole mesh on the device, ``tiled_rounds_device``
decimates it in rounds there: each tile (cut along the mesh's longest side) is split off, decimated with the
vertices it shares pinned, and joined back, all on the device. Else the mesh goes to the host (``HostMesh``) and
``finish_host`` decimates it in rounds: each round cuts it into z tiles of about equal face counts that fit the
budget, pins the vertices a tile shares with another, decimates each tile on the device with the quadrics carried
from earlier rounds, and joins the pieces again. The next round's cuts fall half a tile further, so the last
round's borders are decimated inside a tile. As soon as the whole mesh fits, one last pass on the device takes it
to the target.

Pinned vertices are never moved, removed or extended, and a collapse that only touches a tile's free vertices
sees their whole stars: the link condition and every other guard hold for the joined mesh, so it keeps the
topology of the input (watertight, 2-manifold, components, Euler characteristic).
"""

from __future__ import annotations

import itertools
import time
from typing import Any

import numpy as np

from engine.memory import DECIMATE_BYTES_PER_FACE
from engine.stages.stream import PIECE_TOLERANCE, HostMesh

MAX_ROUNDS = 8
SEAM_MAX_PASSES = 60  # the seams' goal may be out of the guards' reach: passes past this win little
MIN_PROGRESS = 0.01  # a round that removes less than this share of the faces ends the rounds
MAX_TILES = 64  # device tiled rounds need tiles of at least this share of the mesh beside it (else: host rounds)
SAMPLE_FACES = 1 << 20  # the device rounds cut at quantiles of about this many faces


def fits(n_faces: int, budget: int | None) -> bool:
    return budget is None or n_faces * DECIMATE_BYTES_PER_FACE <= budget


def to_host(pos: Any, faces: Any) -> HostMesh:
    """A device mesh on the host, without quadrics yet (the tiles compute them from their faces)."""
    p = pos.numpy().reshape(-1, 3).astype(np.float32)
    lo, hi = (p.min(axis=0), p.max(axis=0)) if len(p) else (np.zeros(3), np.zeros(3))
    origin = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
    return HostMesh(p, faces.numpy().reshape(-1, 3).astype(np.int32), np.zeros((0, 10)), origin)


def decimate_within(
    pos: Any, faces: Any, target: int, budget: int | None, dev: Any, **kwargs: Any
) -> tuple[Any, Any, dict[str, Any]]:
    """``decimate_device`` on ``dev`` within ``budget`` bytes of its memory: ``(pos, faces, info)``, arrays on
    ``dev`` (a mesh elsewhere, e.g. on the host, is taken there or tiled from where it is)."""
    from engine.stages.decimate import decimate_device
    from engine.stages.devmesh import on_device

    if fits(len(faces), budget):
        p, f, st = decimate_device(*on_device(dev, pos, faces), target, **kwargs)
        return p, f, {"tiled": False, **st.to_dict()}
    if pos.device == dev and budget is not None:  # tiled rounds without leaving the device, where tiles fit beside it
        mesh = [pos, faces]
        del pos, faces
        done, why = tiled_rounds_device(mesh, target, budget, **kwargs)
        if done is not None:
            return (*done, why)
        pos, faces = mesh
    host = to_host(pos, faces)
    del pos, faces
    return finish_host(host, target, budget, dev, **kwargs)


def finish_host(
    mesh: HostMesh, target: int, budget: int | None, dev: Any, **kwargs: Any
) -> tuple[Any, Any, dict[str, Any]]:
    """Decimate a host mesh to ``target`` faces within ``budget`` (tiled rounds, then one pass on the device once
    the mesh fits); the result is on the device."""
    import warp as wp

    from engine.kernels.decimate import quadric

    t0 = time.perf_counter()
    rounds: list[dict[str, Any]] = []
    shift = 0.5
    while _another_round(len(mesh.faces), target, budget, rounds):
        before = len(mesh.faces)
        mesh, info = tiled_round(mesh, target, budget, dev, shift, **kwargs)
        rounds.append(info)
        shift = 0.5 - shift
        if len(mesh.faces) > before * (1 - MIN_PROGRESS):
            break
    with wp.ScopedDevice(dev):
        pos = wp.array(mesh.pos, dtype=wp.vec3)
        faces = wp.array(mesh.faces, dtype=wp.vec3i)
        last = len(mesh.quad) and len(mesh.faces) > target and fits(len(mesh.faces), budget)
        quad = wp.array(mesh.quad, dtype=quadric) if last else None
    return final_pass(pos, faces, quad, mesh.origin, target, budget, {"tiled": True, "rounds": rounds}, t0)


def final_pass(
    pos: Any, faces: Any, quad: Any, origin: np.ndarray, target: int, budget: int | None, info: dict, t0: float
) -> tuple[Any, Any, dict[str, Any]]:
    """The last pass on the device across every border, when the mesh fits (quadrics carried, if any)."""
    import warp as wp

    from engine.stages.decimate import decimate_carrying

    with wp.ScopedDevice(pos.device):
        if len(faces) > target and fits(len(faces), budget):
            res = decimate_carrying(pos, faces, target, quadrics=quad, origin=wp.vec3d(*origin), carry=False)
            pos, faces = res.pos, res.faces
            info["final_pass"] = res.stats.to_dict()
    info.update(output_faces=len(faces), seconds=time.perf_counter() - t0)
    return pos, faces, info


def finish_groups(
    host: HostMesh | None,
    pieces: list[Any] | None,
    origin: np.ndarray,
    target: int,
    budget: int | None,
    borders: list[float],
    seam_mm: float,
) -> tuple[Any, Any, dict[str, Any]]:
    """Finish a decimation begun in groups of slabs (``engine.stages.stream``): one last pass on the device where
    they are and fit; otherwise across the ``borders`` (a seam pass on the faces within ``seam_mm`` of them),
    then tiled rounds if still needed. ``pieces``: ``[pos, faces, quad]`` on the device, emptied (the finish owns
    the mesh from here, so that no earlier version of it outlives its replacement)."""
    import warp as wp

    t0 = time.perf_counter()
    info: dict[str, Any] = {"tiled": True, "rounds": []}
    if pieces is None and host is not None and borders and seams_fit_beside(len(host.pos), len(host.faces), budget):
        # groups spilled to the host while the volume streamed, but the joined mesh fits the device seam pass: it
        # goes back up (with its quadrics where the last pass fits too)
        from engine.kernels.decimate import quadric

        carry = len(host.quad) == len(host.pos) and fits(len(host.faces), budget)
        quad = wp.array(host.quad, dtype=quadric) if carry else None
        pieces = [wp.array(host.pos, dtype=wp.vec3), wp.array(host.faces, dtype=wp.vec3i), quad]
        info["uploaded"] = {"faces": len(host.faces), "why": "the spilled groups fit the device seam pass"}
        host = None
    if pieces is not None:
        pos, faces, quad = pieces
        pieces.clear()  # the caller's list: from here these names alone hold the mesh, so it is freed when replaced
        if fits(len(faces), budget):
            return final_pass(pos, faces, quad, origin, target, budget, info, t0)
        if borders:
            mesh = [pos, faces]
            del pos, faces
            (pos, faces), seams = seam_passes_device(mesh, borders, seam_mm, target, budget)
            info["borders"], info["seams"] = len(borders), seams
            if seams["complete"]:
                info.update(output_faces=len(faces), seconds=time.perf_counter() - t0)
                return pos, faces, info
            info["seams_device"] = info.pop("seams")  # the host's seam pass finishes the borders not done
            borders = seams["remaining"]
            if seams["batches"]:
                quad = None  # the vertices were renumbered: the host pass takes quadrics of the current faces
        dev = pos.device
        q = quad.numpy().reshape(-1, 10) if quad is not None else np.zeros((0, 10))
        host = HostMesh(pos.numpy().reshape(-1, 3), faces.numpy().reshape(-1, 3), q, origin)
        del pos, faces, quad, pieces
    else:
        dev = wp.get_device()
    assert host is not None
    if borders and len(host.faces) > target:
        host, info["seams"] = seam_pass(host, borders, seam_mm, target, budget, dev)
    pos, faces, more = finish_host(host, target, budget, dev)
    more["rounds"] = more.get("rounds", [])
    info.update(more)
    info["seconds"] = time.perf_counter() - t0
    return pos, faces, info


def _tile_of_faces(mesh: HostMesh, n_tiles: int, shift: float) -> np.ndarray:
    """Each face's tile: z cuts at equal face counts (by the z of the face's first vertex), offset by ``shift``
    of a tile."""
    z = mesh.pos[mesh.faces[:, 0], 0]
    qs = np.arange(1, n_tiles) / n_tiles if shift == 0 else (np.arange(1, n_tiles + 1) - shift) / n_tiles
    cuts = np.quantile(z, qs)
    return np.searchsorted(cuts, z, side="right").astype(np.int32)


def tiled_round(
    mesh: HostMesh, target: int, budget: int | None, dev: Any, shift: float, **kwargs: Any
) -> tuple[HostMesh, dict[str, Any]]:
    """One round: z tiles that fit ``budget``, each decimated on the device with the vertices it shares pinned,
    toward its share of ``target``."""
    n_faces = len(mesh.faces)
    cap = max(int(budget // DECIMATE_BYTES_PER_FACE), 1) if budget else n_faces
    n_tiles = max(2, -(-n_faces // max(cap * 9 // 10, 1)))
    tile = _tile_of_faces(mesh, n_tiles, shift)
    counts = np.bincount(tile)
    goals = {t: max(round(int(c) * target / n_faces), 1) for t, c in enumerate(counts) if c}
    return decimate_tiles(mesh, tile, goals, dev, **kwargs)


def seam_pass(
    mesh: HostMesh, borders_z: list[float], width_mm: float, target: int, budget: int | None, dev: Any, **kwargs: Any
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
    if not fits(n_seam, budget):
        return mesh, {"skipped": {"seam_faces": n_seam, "budget_bytes": budget}}
    goal = max(n_seam - (len(mesh.faces) - target), 1)
    return decimate_tiles(mesh, tile, {0: goal}, dev, **kwargs)


def _shared_vertices(faces: np.ndarray, order: np.ndarray, bounds: np.ndarray, n: int) -> np.ndarray:
    """The vertices used by faces of more than one tile (tile ``t``: faces ``order[bounds[t]:bounds[t + 1]]``)."""
    tiles = np.zeros(n, np.int32)  # how many tiles use each vertex
    for t in range(len(bounds) - 1):
        used = np.zeros(n, bool)
        used[faces[order[bounds[t] : bounds[t + 1]]].ravel()] = True
        tiles += used
    return tiles >= 2


def seam_passes_device(
    mesh: list[Any], borders_z: list[float], width_mm: float, target: int, budget: int | None
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


SEAM_BYTES_PER_FACE = 12 + DECIMATE_BYTES_PER_FACE  # a seam's (or tile's) face: split off, then decimated


def _seam_base(n_verts: int, n_faces: int) -> tuple[int, int]:
    """What a seam pass over a mesh needs besides ``SEAM_BYTES_PER_FACE`` per seam face, and the least it needs:
    the mesh (its callers hold it) and its joined copy; at least the mesh three times over (the joined copy and
    the compacted result; measured on the CPU: up to 1.46x the first term alone, small seams)."""
    mesh = (n_faces + n_verts) * 12
    return mesh + n_faces * 12, 3 * mesh


def _seam_need(n_verts: int, n_faces: int, n_seam: int) -> int:
    """Device bytes of a seam pass over ``n_seam`` of a mesh's faces: the seam split off and decimated beside the
    mesh, then joined back (``_seam_base``)."""
    base, least = _seam_base(n_verts, n_faces)
    return max(base + n_seam * SEAM_BYTES_PER_FACE, least)


def seams_fit_beside(n_verts: int, n_faces: int, budget: int | None) -> bool:
    """Whether a mesh this size leaves room within ``budget`` for a device seam pass (of at least one small seam)."""
    return budget is None or _seam_need(n_verts, n_faces, 0) <= budget


def seam_pass_device(
    pos: Any,
    faces: Any,
    borders_z: list[float],
    width_mm: float,
    target: int,
    budget: int | None,
    keep: float | None = None,
) -> tuple[tuple[Any, Any] | None, dict[str, Any]]:
    """``seam_pass`` on a device mesh, where the seam's decimation fits ``budget`` beside the mesh: the seam's faces
    are decimated (quadrics from the current faces), pinned where they meet the rest, down to the mesh's ``target``
    (or to ``keep`` of the seam's faces). ``((pos, faces), info)``, or ``(None, why)`` where it does not fit."""
    import warp as wp

    from engine.kernels import tiles as kt

    n_faces = len(faces)

    def flags(flag: Any) -> None:
        borders = wp.array(np.asarray(borders_z, np.float32), dtype=wp.float32)
        wp.launch(kt.seam_flags, dim=n_faces, inputs=[pos, faces, borders, float(width_mm), flag])

    def goal(n_seam: int) -> int:
        return max(n_seam - (n_faces - target) if keep is None else round(keep * n_seam), 1)

    return _flagged_pass_device(pos, faces, flags, goal, budget, max_passes=SEAM_MAX_PASSES)


def _flagged_pass_device(
    pos: Any, faces: Any, flags: Any, goal_of: Any, budget: int | None, **options: Any
) -> tuple[tuple[Any, Any] | None, dict[str, Any]]:
    """Decimate the faces that ``flags(flag)`` flags (1 in an int32 per face: a seam or a z tile) on the device
    beside the rest of the mesh, where that fits ``budget``: split off, pinned where they meet the rest, decimated
    to ``goal_of(flagged faces)`` (quadrics from the current faces; ``options`` for ``decimate_carrying``) and
    joined back. ``((pos, faces), info)``, or
    ``(None, why)`` where it does not fit. The caller's ``pos`` and ``faces`` may be freed once it returns."""
    import warp as wp

    from engine.kernels import decimate as kd
    from engine.kernels import tiles as kt
    from engine.stages.decimate import decimate_carrying
    from engine.stages.devmesh import compact_vertices, exclusive_scan

    t0 = time.perf_counter()
    n_faces, n_verts = len(faces), len(pos)
    with wp.ScopedDevice(pos.device):
        flag = wp.empty(n_faces, dtype=wp.int32)
        flags(flag)
        slot, n_seam = exclusive_scan(flag)
        need = _seam_need(n_verts, n_faces, n_seam)
        if n_seam == 0 or (budget is not None and need > budget):
            return None, {"seam_faces": n_seam, "faces": n_faces, "need_bytes": need, "budget_bytes": budget}
        in_seam = wp.zeros(n_verts, dtype=wp.int32)
        in_rest = wp.zeros(n_verts, dtype=wp.int32)
        wp.launch(kt.mark_used, dim=n_faces, inputs=[faces, flag, 1, in_seam])
        wp.launch(kt.mark_used, dim=n_faces, inputs=[faces, flag, 0, in_rest])
        vslot, n_local = exclusive_scan(in_seam)
        seam = wp.empty(n_seam, dtype=wp.vec3i)
        rest = wp.empty(n_faces - n_seam, dtype=wp.vec3i)
        wp.launch(kt.split_faces, dim=n_faces, inputs=[faces, flag, slot, vslot, seam, rest])
        del flag, slot
        vids = wp.empty(n_local, dtype=wp.int32)
        local_pos = wp.empty(n_local, dtype=wp.vec3)
        lock = wp.empty(n_local, dtype=wp.int32)
        wp.launch(kt.gather_seam, dim=n_verts, inputs=[pos, in_seam, in_rest, vslot, vids, local_pos, lock])
        del in_seam, in_rest, vslot
        res = decimate_carrying(local_pos, seam, goal_of(n_seam), locked=lock, **options)
        del local_pos, seam
        n_out = len(res.pos)
        new = wp.empty(n_out, dtype=wp.int32)
        wp.launch(kt.new_vertex_flags, dim=n_out, inputs=[res.kept, lock, new])
        new_slot, n_new = exclusive_scan(new)
        out_id = wp.empty(n_out, dtype=wp.int32)
        joined_pos = wp.empty(n_verts + n_new, dtype=wp.vec3)
        wp.copy(joined_pos, pos, count=n_verts)
        new_pos = wp.empty(max(n_new, 1), dtype=wp.vec3)
        join = [res.pos, res.kept, lock, vids, new_slot, n_verts, out_id, new_pos]
        wp.launch(kt.join_seam, dim=n_out, inputs=join)
        if n_new:
            wp.copy(joined_pos, new_pos, dest_offset=n_verts, count=n_new)
        wp.launch(kd.remap_faces, dim=len(res.faces), inputs=[res.faces, out_id])
        joined = wp.empty(len(rest) + len(res.faces), dtype=wp.vec3i)
        wp.copy(joined, rest, count=len(rest))
        wp.copy(joined, res.faces, dest_offset=len(rest), count=len(res.faces))
        del rest, pos, faces
        out_pos, out_faces = compact_vertices(joined_pos, joined)  # drops the seam's replaced vertices
    pinned = res.stats.vertex_classes.get("locked")
    info = {"faces_in": n_faces, "seam_faces_in": n_seam, "seam_faces_out": len(res.faces), "pinned": pinned}
    info.update(faces_out=len(out_faces), passes=res.stats.passes, seconds=time.perf_counter() - t0, on="device")
    return (out_pos, out_faces), info


def _tile_room(n_verts: int, n_faces: int, budget: int) -> int:
    """The most faces a tile of a device mesh may have for its pass beside the mesh (``_seam_need`` within
    ``budget``), 0 if none."""
    base, least = _seam_base(n_verts, n_faces)
    return 0 if least > budget else max((budget - base) // SEAM_BYTES_PER_FACE, 0)


def _another_round(n_faces: int, target: int, budget: int | None, rounds: list[Any]) -> bool:
    """Whether tiled rounds go on: the mesh does not fit for the last pass yet, is not within the tiles' tolerance
    of ``target``, and the rounds are not used up."""
    return not fits(n_faces, budget) and n_faces > target * (1 + PIECE_TOLERANCE) and len(rounds) < MAX_ROUNDS


def tiled_rounds_device(
    mesh: list[Any], target: int, budget: int, **options: Any
) -> tuple[tuple[Any, Any] | None, dict[str, Any]]:
    """``finish_host``'s tiled rounds without leaving the device: each round cuts the mesh (``mesh``: ``[pos,
    faces]``, emptied) along its longest side into tiles whose pass fits ``budget`` beside it
    (``_flagged_pass_device``; a tile found too large is halved), decimates each toward its share of ``target``
    with its borders pinned, and the next round's cuts fall half a tile further; then, once the mesh fits, one pass
    takes it to ``target``. The tiles start from the quadrics of their current faces (the host rounds carry them).
    ``(None, why)`` with the mesh left in ``mesh`` where not even a small tile fits beside it."""
    import warp as wp

    from engine.kernels import tiles as kt
    from engine.stages.decimate import decimate_device

    t0 = time.perf_counter()
    pos, faces = mesh
    rounds: list[dict[str, Any]] = []
    shift = 0.5
    while _another_round(len(faces), target, budget, rounds):
        n_faces = len(faces)
        cap = _tile_room(len(pos), n_faces, budget)
        if cap < max(n_faces // MAX_TILES, 1):
            mesh[:] = [pos, faces]
            return None, {"tile_faces_room": cap, "faces": n_faces, "budget_bytes": budget}
        n_tiles = max(2, -(-n_faces // max(cap * 9 // 10, 1)))
        stride = max(n_faces // SAMPLE_FACES, 1)
        with wp.ScopedDevice(pos.device):
            pts = wp.empty(n_faces // stride, dtype=wp.vec3)
            wp.launch(kt.face_sample, dim=len(pts), inputs=[pos, faces, stride, pts])
            pts_np = pts.numpy()
        axis = int(np.argmax(np.ptp(pts_np, axis=0)))  # the tiles cut the longest side (a plate: not across it)
        sample = np.sort(pts_np[:, axis])
        qs = (np.arange(1, n_tiles + 1) - shift) / n_tiles if shift else np.arange(1, n_tiles) / n_tiles
        cuts = [-np.inf, *np.quantile(sample, qs[qs < 1]), np.inf]
        queue = list(itertools.pairwise(cuts))
        info: dict[str, Any] = {"faces_in": n_faces, "axis": "zyx"[axis], "tiles": [], "on": "device"}
        while queue:
            z0, z1 = queue.pop(0)
            zr = (float(z0), float(z1))

            def flags(flag: Any, p: Any = pos, f: Any = faces, zr: tuple[float, float] = zr, ax: int = axis) -> None:
                wp.launch(kt.range_flags, dim=len(f), inputs=[p, f, ax, *zr, flag])

            def goal(n_tile: int, n: int = n_faces) -> int:
                return max(round(n_tile * target / n), 1)

            done, why = _flagged_pass_device(pos, faces, flags, goal, budget, stop_tolerance=PIECE_TOLERANCE, **options)
            if done is None:
                inside = sample[(sample >= z0) & (sample < z1)]
                if why["seam_faces"] == 0 or len(inside) < 2 or not inside[0] < np.median(inside) < inside[-1]:
                    continue  # nothing there, or a tile that cannot be cut further: left as it is this round
                mid = float(np.median(inside))
                queue[:0] = [(z0, mid), (mid, z1)]
                continue
            (pos, faces) = done
            tile = {"faces_in": why["seam_faces_in"], "faces_out": why["seam_faces_out"], "pinned": why["pinned"]}
            info["tiles"].append(tile)
        info.update(faces_out=len(faces), seconds=time.perf_counter() - t0)
        rounds.append(info)
        shift = 0.5 - shift
        if len(faces) > n_faces * (1 - MIN_PROGRESS):
            break
    out: dict[str, Any] = {"tiled": True, "on": "device", "rounds": rounds}
    if len(faces) > target and fits(len(faces), budget):
        pos, faces, st = decimate_device(pos, faces, target, **options)
        out["final_pass"] = st.to_dict()
    mesh.clear()
    out["seconds"] = time.perf_counter() - t0
    return (pos, faces), out


def decimate_tiles(
    mesh: HostMesh, tile: np.ndarray, goals: dict[int, int], dev: Any, **kwargs: Any
) -> tuple[HostMesh, dict[str, Any]]:
    """Decimate the tiles named in ``goals`` (tile id -> faces to reach) on the device, each with the vertices it
    shares with another tile pinned and its quadrics carried; the other tiles' faces are kept as they are."""
    import warp as wp

    from engine.kernels.decimate import quadric
    from engine.stages.decimate import decimate_carrying

    t0 = time.perf_counter()
    n_faces, n_verts = len(mesh.faces), len(mesh.pos)
    tile = tile.astype(np.int16)
    order = np.argsort(tile, kind="stable")
    bounds = np.searchsorted(tile[order], np.arange(int(tile.max()) + 2))
    shared = _shared_vertices(mesh.faces, order, bounds, n_verts)
    carried = len(mesh.quad) == n_verts
    quad = mesh.quad if carried else np.zeros((n_verts, 10))
    times = {"split": time.perf_counter() - t0, "tiles": 0.0, "decimate": 0.0}
    new_pos, new_quad, new_faces = [mesh.pos], [quad], []
    n_total = n_verts
    alive = np.ones(n_verts, bool)
    tiles = []
    for t in range(len(bounds) - 1):
        fidx = order[bounds[t] : bounds[t + 1]]
        if len(fidx) == 0:
            continue
        t1 = time.perf_counter()
        tf = mesh.faces[fidx]
        if t not in goals:  # kept as it is
            new_faces.append(tf)
            continue
        used = np.zeros(n_verts, bool)
        used[tf.ravel()] = True
        vids = np.flatnonzero(used)
        lut = np.empty(n_verts, np.int32)
        lut[vids] = np.arange(len(vids), dtype=np.int32)
        pinned = shared[vids]
        goal = goals[t]
        with wp.ScopedDevice(dev):
            res = decimate_carrying(
                wp.array(mesh.pos[vids], dtype=wp.vec3),
                wp.array(lut[tf], dtype=wp.vec3i),
                goal,
                locked=wp.array(pinned.astype(np.int32), dtype=wp.int32),
                quadrics=wp.array(quad[vids], dtype=quadric) if carried else None,
                origin=wp.vec3d(*mesh.origin),
                **{"stop_tolerance": PIECE_TOLERANCE, **kwargs},
            )
            out_pos, out_faces = res.pos.numpy().reshape(-1, 3), res.faces.numpy().reshape(-1, 3)  # sync point
            out_quad, kept = res.quad.numpy().reshape(-1, 10), res.kept.numpy()
        times["decimate"] += res.stats.seconds
        keep_id = vids[kept]
        was_pinned = pinned[kept]
        alive[vids[~pinned]] = False  # the tile's free vertices are replaced by its output
        out_lut = np.where(was_pinned, keep_id, n_total + np.cumsum(~was_pinned) - 1)
        if not carried:
            quad[keep_id[was_pinned]] += out_quad[was_pinned]  # each tile's share of a shared vertex's quadric
        new_pos.append(out_pos[~was_pinned])
        new_quad.append(out_quad[~was_pinned])
        new_faces.append(out_lut[out_faces])
        n_total += int((~was_pinned).sum())
        tiles.append({"faces_in": len(tf), "faces_out": len(out_faces), "pinned": int(pinned.sum())})
        times["tiles"] += time.perf_counter() - t1
    t1 = time.perf_counter()
    faces = np.concatenate(new_faces)
    pos = np.concatenate(new_pos)
    quad_all = np.concatenate(new_quad)
    keep = np.concatenate([alive, np.ones(n_total - n_verts, bool)])
    remap = np.cumsum(keep) - 1
    out = HostMesh(pos[keep], remap[faces].astype(np.int32), quad_all[keep], mesh.origin)
    times["join"] = time.perf_counter() - t1
    info = {"tiles": tiles, "faces_in": n_faces, "faces_out": len(out.faces), "seconds": time.perf_counter() - t0}
    return out, info | {"timings": times}
