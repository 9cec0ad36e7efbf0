"""Stage: decimation of a mesh too large for the device memory budget, tile by tile with pinned tile borders.

``decimate_within`` decimates a device mesh in one piece where its decimation fits the budget, as
``decimate_device`` does. Otherwise the mesh goes to the host (``HostMesh``) and ``finish_host`` decimates it in
rounds: each round cuts it into z tiles of about equal face counts that fit the budget, pins the vertices a tile
shares with another, decimates each tile on the device with the quadrics carried from earlier rounds, and joins
the pieces again. The next round's cuts fall half a tile further, so the last round's borders are decimated
inside a tile. As soon as the whole mesh fits, one last pass on the device takes it to the target.

Pinned vertices are never moved, removed or extended, and a collapse that only touches a tile's free vertices
sees their whole stars: the link condition and every other guard hold for the joined mesh, so it keeps the
topology of the input (watertight, 2-manifold, components, Euler characteristic).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from engine.memory import DECIMATE_BYTES_PER_FACE
from engine.stages.stream import PIECE_TOLERANCE, HostMesh

MAX_ROUNDS = 8
MIN_PROGRESS = 0.01  # a round that removes less than this share of the faces ends the rounds


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
    """``decimate_device`` within ``budget`` bytes of device memory: ``(pos, faces, info)``, device arrays."""
    from engine.stages.decimate import decimate_device

    if fits(len(faces), budget):
        p, f, st = decimate_device(pos, faces, target, **kwargs)
        return p, f, {"tiled": False, **st.to_dict()}
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
    # rounds until the mesh fits for the last pass, or is within the tiles' tolerance of the target
    while (
        not fits(len(mesh.faces), budget)
        and len(mesh.faces) > target * (1 + PIECE_TOLERANCE)
        and len(rounds) < MAX_ROUNDS
    ):
        before = len(mesh.faces)
        mesh, info = tiled_round(mesh, target, budget, dev, shift, **kwargs)
        rounds.append(info)
        shift = 0.5 - shift
        if len(mesh.faces) > before * (1 - MIN_PROGRESS):
            break
    with wp.ScopedDevice(dev):
        pos = wp.array(mesh.pos, dtype=wp.vec3)
        faces = wp.array(mesh.faces, dtype=wp.vec3i)
        quad = wp.array(mesh.quad, dtype=quadric) if len(mesh.quad) else None
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
    host: HostMesh | None, pieces: tuple[Any, Any, Any] | None, origin: np.ndarray, target: int, budget: int | None
) -> tuple[Any, Any, dict[str, Any]]:
    """Finish a decimation begun in groups of slabs (``engine.stages.stream``): on the device where they are and
    fit, else through the host in tiled rounds."""
    t0 = time.perf_counter()
    if pieces is not None:
        pos, faces, quad = pieces
        if fits(len(faces), budget):
            return final_pass(pos, faces, quad, origin, target, budget, {"tiled": True, "rounds": []}, t0)
        dev = pos.device
        host = HostMesh(pos.numpy().reshape(-1, 3), faces.numpy().reshape(-1, 3), quad.numpy().reshape(-1, 10), origin)
        del pos, faces, quad, pieces
    else:
        import warp as wp

        dev = wp.get_device()
    assert host is not None
    return finish_host(host, target, budget, dev)


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
    import warp as wp

    from engine.kernels.decimate import quadric
    from engine.stages.decimate import decimate_carrying

    t0 = time.perf_counter()
    n_faces, n_verts = len(mesh.faces), len(mesh.pos)
    cap = max(int(budget // DECIMATE_BYTES_PER_FACE), 1) if budget else n_faces
    n_tiles = max(2, -(-n_faces // max(cap * 9 // 10, 1)))
    tile = _tile_of_faces(mesh, n_tiles, shift)
    order = np.argsort(tile, kind="stable")
    bounds = np.searchsorted(tile[order], np.arange(tile.max() + 2))
    refs = mesh.faces.ravel()
    ftile = np.repeat(tile, 3)
    lo = np.full(n_verts, np.iinfo(np.int32).max, np.int32)
    hi = np.full(n_verts, -1, np.int32)
    np.minimum.at(lo, refs, ftile)
    np.maximum.at(hi, refs, ftile)
    shared = lo != hi
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
        used = np.zeros(n_verts, bool)
        used[tf.ravel()] = True
        vids = np.flatnonzero(used)
        lut = np.empty(n_verts, np.int32)
        lut[vids] = np.arange(len(vids), dtype=np.int32)
        pinned = shared[vids]
        goal = max(round(len(tf) * target / n_faces), 1)
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
