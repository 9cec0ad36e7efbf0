"""Decimation of a mesh too large for the device memory budget, tile by tile with pinned tile borders.

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
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, VEC10D
from engine.backend.select import backend_of, get_backend
from engine.budget import Budget, BudgetSpec
from engine.decimation import kernel_specs as K
from engine.decimation.pieces import decimate_piece_device, piece_room

PIECE_TOLERANCE = 0.01  # a group or tile stops this close to its share (the last pass across them is exact)
MAX_ROUNDS = 8
MIN_PROGRESS = 0.01  # a round that removes less than this share of the faces ends the rounds
SAMPLE_FACES = 1 << 20  # the device rounds cut at quantiles of about this many faces


@dataclass
class HostMesh:
    """A mesh being decimated piece by piece, on the host: float32 (z, y, x) positions, int32 faces, and each
    vertex's accumulated quadric (float64, 10 coefficients, about ``origin``)."""

    pos: np.ndarray
    faces: np.ndarray
    quad: np.ndarray
    origin: np.ndarray

    def release(self) -> None:
        """Let go of the arrays: the mesh was consumed (what is kept of it is in its replacement, or on the
        device), so that no reference to it elsewhere holds a copy."""
        self.pos, self.faces, self.quad = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 10))


def to_host(pos: Any, faces: Any) -> HostMesh:
    """A device mesh on the host, without quadrics yet (the tiles compute them from their faces)."""
    be = backend_of(pos)
    p = be.to_host(pos).reshape(-1, 3).astype(np.float32)
    lo, hi = (p.min(axis=0), p.max(axis=0)) if len(p) else (np.zeros(3), np.zeros(3))
    origin = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
    return HostMesh(p, be.to_host(faces).reshape(-1, 3).astype(np.int32), np.zeros((0, 10)), origin)


def decimate_within(
    pos: Any, faces: Any, target: int, budget: BudgetSpec, dev: Any, **kwargs: Any
) -> tuple[Any, Any, dict[str, Any]]:
    """``decimate_device`` on ``dev`` within ``budget`` of its memory (a ``Budget``, or bytes as ``Budget.of``
    reads them): ``(pos, faces, info)``, arrays on ``dev`` (a Warp device or spec, ``"opencl[:N]"`` or an
    ``engine.backend.Backend``; a mesh elsewhere, e.g. on the host, is taken there or tiled from where it is)."""
    from engine.decimation.passes import decimate_device
    from engine.surface.devmesh import on_device

    budget = Budget.of(budget)
    dev = get_backend(dev)
    if budget.fits_decimation(len(faces)):
        p, f, st = decimate_device(*on_device(dev, pos, faces), target, **kwargs)
        return p, f, {"tiled": False, **st.to_dict()}
    if backend_of(pos) is dev and budget.limited:  # tiled rounds without leaving the device, where tiles fit beside it
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
    mesh: HostMesh, target: int, budget: Budget, dev: Any, **kwargs: Any
) -> tuple[Any, Any, dict[str, Any]]:
    """Decimate a host mesh to ``target`` faces within ``budget`` (tiled rounds, then one pass on the device once
    the mesh fits); the result is on the device ``dev`` (as for ``decimate_within``). ``mesh`` is consumed
    (``HostMesh.release``)."""
    be = get_backend(dev)
    t0 = time.perf_counter()
    rounds: list[dict[str, Any]] = []
    shift = 0.5
    while _another_round(len(mesh.faces), target, budget, rounds):
        before = len(mesh.faces)
        mesh, info = tiled_round(mesh, target, budget, be, shift, **kwargs)
        rounds.append(info)
        shift = 0.5 - shift
        if len(mesh.faces) > before * (1 - MIN_PROGRESS):
            break
    pos, faces = be.from_host(mesh.pos, VEC3F), be.from_host(mesh.faces, VEC3I)
    last = len(mesh.quad) and len(mesh.faces) > target and budget.fits_decimation(len(mesh.faces))
    quad = be.from_host(mesh.quad, VEC10D) if last else None
    mesh.release()  # on the device now (the caller's reference to it holds nothing)
    return final_pass(pos, faces, quad, mesh.origin, target, budget, {"tiled": True, "rounds": rounds}, t0)


def final_pass(
    pos: Any, faces: Any, quad: Any, origin: np.ndarray, target: int, budget: Budget, info: dict, t0: float
) -> tuple[Any, Any, dict[str, Any]]:
    """The last pass on the device across every border, when the mesh fits (quadrics carried, if any)."""
    from engine.decimation.passes import decimate_carrying

    if len(faces) > target and budget.fits_decimation(len(faces)):
        res = decimate_carrying(pos, faces, target, quadrics=quad, origin=origin, carry=False)
        pos, faces = res.pos, res.faces
        info["final_pass"] = res.stats.to_dict()
    info.update(output_faces=len(faces), seconds=time.perf_counter() - t0)
    return pos, faces, info


def _tile_of_faces(mesh: HostMesh, n_tiles: int, shift: float) -> np.ndarray:
    """Each face's tile: z cuts at equal face counts (by the z of the face's first vertex), offset by ``shift``
    of a tile."""
    z = mesh.pos[mesh.faces[:, 0], 0]
    qs = np.arange(1, n_tiles) / n_tiles if shift == 0 else (np.arange(1, n_tiles + 1) - shift) / n_tiles
    cuts = np.quantile(z, qs)
    return np.searchsorted(cuts, z, side="right").astype(np.int32)


def tiled_round(
    mesh: HostMesh, target: int, budget: Budget, dev: Any, shift: float, **kwargs: Any
) -> tuple[HostMesh, dict[str, Any]]:
    """One round: z tiles that fit ``budget``, each decimated on the device with the vertices it shares pinned,
    toward its share of ``target``."""
    n_faces = len(mesh.faces)
    cap = max(int(budget.bytes // budget.costs.decimate), 1) if budget.bytes else n_faces
    n_tiles = max(2, -(-n_faces // max(cap * 9 // 10, 1)))
    tile = _tile_of_faces(mesh, n_tiles, shift)
    counts = np.bincount(tile)
    goals = {t: max(round(int(c) * target / n_faces), 1) for t, c in enumerate(counts) if c}
    return decimate_tiles(mesh, tile, goals, dev, **kwargs)


def _shared_vertices(faces: np.ndarray, order: np.ndarray, bounds: np.ndarray, n: int) -> np.ndarray:
    """The vertices used by faces of more than one tile (tile ``t``: faces ``order[bounds[t]:bounds[t + 1]]``)."""
    tiles = np.zeros(n, np.int32)  # how many tiles use each vertex
    for t in range(len(bounds) - 1):
        used = np.zeros(n, bool)
        used[faces[order[bounds[t] : bounds[t + 1]]].ravel()] = True
        tiles += used
    return tiles >= 2


def decimate_tiles(
    mesh: HostMesh, tile: np.ndarray, goals: dict[int, int], dev: Any, **kwargs: Any
) -> tuple[HostMesh, dict[str, Any]]:
    """Decimate the tiles named in ``goals`` (tile id -> faces to reach) on the device, each with the vertices it
    shares with another tile pinned and its quadrics carried; the other tiles' faces are kept as they are.

    ``mesh`` is consumed (``HostMesh.release``): a host bound holds the mesh, what the tiles give back and the
    joined result, never copies of each (``_Joined``)."""
    from engine.decimation.passes import decimate_carrying

    be = get_backend(dev)
    t0 = time.perf_counter()
    n_faces, n_verts = len(mesh.faces), len(mesh.pos)
    tile = tile.astype(np.int16)
    order = np.argsort(tile, kind="stable").astype(np.int32)
    bounds = np.searchsorted(tile[order], np.arange(int(tile.max()) + 2))
    del tile
    shared = _shared_vertices(mesh.faces, order, bounds, n_verts)
    carried = len(mesh.quad) == n_verts
    joined = _Joined(mesh, shared, carried)
    times = {"split": time.perf_counter() - t0, "tiles": 0.0, "decimate": 0.0}
    tiles = []
    for t in range(len(bounds) - 1):
        fidx = order[bounds[t] : bounds[t + 1]]
        if len(fidx) == 0:
            continue
        t1 = time.perf_counter()
        tf = mesh.faces[fidx]
        if t not in goals:  # kept as it is
            joined.add_faces(tf)
            continue
        used = np.zeros(n_verts, bool)
        used[tf.ravel()] = True
        vids = np.flatnonzero(used)
        del used
        lut = np.empty(n_verts, np.int32)
        lut[vids] = np.arange(len(vids), dtype=np.int32)
        local = lut[tf]
        del lut, tf
        pinned = shared[vids]
        res = decimate_carrying(
            be.from_host(mesh.pos[vids], VEC3F),
            be.from_host(local, VEC3I),
            goals[t],
            locked=be.from_host(pinned.astype(np.int32)),
            quadrics=be.from_host(mesh.quad[vids], VEC10D) if carried else None,
            origin=mesh.origin,
            **{"stop_tolerance": PIECE_TOLERANCE, **kwargs},
        )
        del local
        out_pos, out_faces = be.to_host(res.pos).reshape(-1, 3), be.to_host(res.faces).reshape(-1, 3)  # sync point
        out_quad, kept = be.to_host(res.quad).reshape(-1, 10), be.to_host(res.kept)
        times["decimate"] += res.stats.seconds
        del res
        joined.add_tile(vids, pinned, kept, out_pos, out_faces, out_quad)
        tiles.append({"faces_in": len(fidx), "faces_out": len(out_faces), "pinned": int(pinned.sum())})
        times["tiles"] += time.perf_counter() - t1
    del order, shared
    t1 = time.perf_counter()
    out = joined.result()
    times["join"] = time.perf_counter() - t1
    info = {"tiles": tiles, "faces_in": n_faces, "faces_out": len(out.faces), "seconds": time.perf_counter() - t0}
    return out, info | {"timings": times}


class _Joined:
    """The tiles' outputs joined into the next mesh as they come, consuming the input ``mesh``.

    A tile's free vertices are replaced by its output's (numbered after the input's: ``n_verts + j``); its pinned
    ones keep their input ids. The faces are written into one array as they come (the input's size, untouched past
    what is written, so only that is resident) and renumbered in place at the end: the kept input vertices in their
    order, then the tiles' new ones. Without carried quadrics, only the shared vertices' are summed (each tile's
    share), the other kept input vertices start from none, as the tiles start from their faces'."""

    def __init__(self, mesh: HostMesh, shared: np.ndarray, carried: bool) -> None:
        self.mesh, self.carried = mesh, carried
        self.n_verts = len(mesh.pos)
        self.alive = np.ones(self.n_verts, bool)
        self.faces = np.empty((len(mesh.faces), 3), np.int32)
        self.n_faces = 0
        self.new_pos: list[np.ndarray] = []
        self.new_quad: list[np.ndarray] = []
        self.n_new = 0
        self.shared_ids = np.zeros(0, np.int64) if carried else np.flatnonzero(shared)
        self.shared_quad = np.zeros((len(self.shared_ids), 10))

    def add_faces(self, faces: np.ndarray) -> None:
        self.faces[self.n_faces : self.n_faces + len(faces)] = faces
        self.n_faces += len(faces)

    def add_tile(
        self,
        vids: np.ndarray,
        pinned: np.ndarray,
        kept: np.ndarray,
        out_pos: np.ndarray,
        out_faces: np.ndarray,
        out_quad: np.ndarray,
    ) -> None:
        keep_id = vids[kept]
        was_pinned = pinned[kept]
        self.alive[vids[~pinned]] = False  # the tile's free vertices are replaced by its output
        fresh = ~was_pinned
        out_lut = np.where(was_pinned, keep_id, self.n_verts + self.n_new + np.cumsum(fresh) - 1).astype(np.int32)
        if not self.carried:  # each tile's share of a shared vertex's quadric
            np.add.at(self.shared_quad, np.searchsorted(self.shared_ids, keep_id[was_pinned]), out_quad[was_pinned])
        self.new_pos.append(out_pos[fresh])
        self.new_quad.append(out_quad[fresh])
        self.n_new += int(fresh.sum())
        self.add_faces(out_lut[out_faces])

    def result(self) -> HostMesh:
        mesh = self.mesh
        n_alive = int(self.alive.sum())
        n_out = n_alive + self.n_new
        remap = (np.cumsum(self.alive, dtype=np.int64) - 1).astype(np.int32)
        faces = self.faces[: self.n_faces]
        step = 1 << 20
        for s in range(0, len(faces), step):  # renumbered in place, a block at a time
            block = faces[s : s + step]
            old = block < self.n_verts
            block[old] = remap[block[old]]
            block[~old] += n_alive - self.n_verts
        mesh.faces = np.zeros((0, 3), np.int32)  # the input let go of as the result takes its place
        pos = np.empty((n_out, 3), np.float32)
        np.compress(self.alive, mesh.pos, axis=0, out=pos[:n_alive])
        mesh.pos = np.zeros((0, 3), np.float32)
        quad = np.zeros((n_out, 10))
        if self.carried:
            np.compress(self.alive, mesh.quad, axis=0, out=quad[:n_alive])
        else:  # shared vertices are pinned in every tile: all kept
            quad[remap[self.shared_ids]] = self.shared_quad
        mesh.quad = np.zeros((0, 10))
        o = n_alive
        for p, q in zip(self.new_pos, self.new_quad, strict=True):
            pos[o : o + len(p)], quad[o : o + len(p)] = p, q
            o += len(p)
        self.new_pos, self.new_quad = [], []
        return HostMesh(pos, faces, quad, mesh.origin)


def _another_round(n_faces: int, target: int, budget: Budget, rounds: list[Any]) -> bool:
    """Whether tiled rounds go on: the mesh does not fit for the last pass yet, is not within the tiles' tolerance
    of ``target``, and the rounds are not used up."""
    return not budget.fits_decimation(n_faces) and n_faces > target * (1 + PIECE_TOLERANCE) and len(rounds) < MAX_ROUNDS


def tiled_rounds_device(
    mesh: list[Any], target: int, budget: Budget, **options: Any
) -> tuple[tuple[Any, Any] | None, dict[str, Any]]:
    """``finish_host``'s tiled rounds without leaving the device: each round cuts the mesh (``mesh``: ``[pos,
    faces]``, emptied) along its longest side into tiles whose pass fits ``budget`` beside it
    (``decimate_piece_device``; a tile found too large is halved), decimates each toward its share of ``target``
    with its borders pinned, and the next round's cuts fall half a tile further; then, once the mesh fits, one pass
    takes it to ``target``. The tiles start from the quadrics of their current faces (the host rounds carry them).
    ``(None, why)`` with the mesh left in ``mesh`` where not even a small tile fits beside it."""
    from engine.decimation.passes import decimate_device

    t0 = time.perf_counter()
    pos, faces = mesh
    be = backend_of(pos)
    rounds: list[dict[str, Any]] = []
    shift = 0.5
    while _another_round(len(faces), target, budget, rounds):
        n_faces = len(faces)
        cap = piece_room(len(pos), n_faces, budget)
        if cap < max(n_faces // budget.max_tiles, 1):
            mesh[:] = [pos, faces]
            return None, {"tile_faces_room": cap, "faces": n_faces, "budget_bytes": budget.bytes}
        n_tiles = max(2, -(-n_faces // max(cap * 9 // 10, 1)))
        stride = max(n_faces // SAMPLE_FACES, 1)
        pts = be.empty(n_faces // stride, VEC3F)
        be.launch(K.FACE_SAMPLE, len(pts), [pos, faces, stride, pts])
        pts_np = be.to_host(pts)
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
                be.launch(K.RANGE_FLAGS, len(f), [p, f, ax, *zr, flag])

            def goal(n_tile: int, n: int = n_faces) -> int:
                return max(round(n_tile * target / n), 1)

            done, why = decimate_piece_device(
                pos, faces, flags, goal, budget, stop_tolerance=PIECE_TOLERANCE, **options
            )
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
    if len(faces) > target and budget.fits_decimation(len(faces)):
        pos, faces, st = decimate_device(pos, faces, target, **options)
        out["final_pass"] = st.to_dict()
    mesh.clear()
    out["seconds"] = time.perf_counter() - t0
    return (pos, faces), out
