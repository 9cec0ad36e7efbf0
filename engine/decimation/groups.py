"""Decimation of a streamed volume's mesh in groups of slabs (``GroupDecimator``), and its finish across the
groups' borders (``finish_groups``).

While the volume streams through the Gaussian and MC33 (``engine.isosurface.stream``), the slabs' meshes are
gathered; when the mesh built so far and its decimation would no longer fit the budget, the slabs gathered so far
are decimated as one group with the vertices they share with the slabs below and above pinned, so the pieces still
join into one watertight surface. The decimated groups are finished by one last pass where they fit, else across
their borders (``engine.decimation.seams``) and then in tiled rounds (``engine.decimation.tiles``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, VEC10D, Backend
from engine.backend.select import backend_of, get_backend
from engine.budget import Budget
from engine.decimation import kernel_specs as K
from engine.decimation.seams import seam_pass, seam_passes_device, seams_fit_beside
from engine.decimation.tiles import PIECE_TOLERANCE, HostMesh, final_pass, finish_host

GROUP_SLACK = 1.15  # groups of slabs keep this many times their share of the target
SEAM_SLACK = 1.03  # or this many, when only the faces near their borders get a last pass (the seams)


class GroupDecimator:
    """Collects slab meshes and decimates them in groups whose decimation fits the budget.

    The decimated groups stay on the device, numbered as one mesh (``pieces``), until they hold ``spill_bytes``;
    then they go to the host (``host``). The vertices a group shares with the group below keep that group's ids;
    each side's share of their quadrics is added at the end (``deferred``).

    Args:
        ratio: the share of its faces a group keeps (with ``slack`` more in "last pass" mode).
        slack: how far above its share of the target a group stops, for the last pass across all groups.
        mesh_room: device bytes for the groups held and a group's decimation.
        spill_bytes: decimated groups held on the device beyond this go to the host.
        origin: the quadrics' origin (z, y, x) mm.
        nz: the volume's planes (to extrapolate the decimated groups' size from the first group).
        dev: the device the groups are decimated on.
        budget: the costs per face and the groups' finish (``Budget.group_mode``: chosen from the first group
            unless set).
    """

    def __init__(
        self,
        ratio: float,
        slack: float,
        mesh_room: int,
        spill_bytes: int,
        origin: np.ndarray,
        nz: int,
        dev: Any,
        budget: Budget,
    ) -> None:
        self.ratio, self.slack, self.mesh_room, self.spill_bytes = ratio, slack, mesh_room, spill_bytes
        self.origin, self.nz, self.dev, self.per_face = origin, nz, dev, budget.costs.decimate
        # "last pass" (groups keep ``slack`` more) or "seams" (groups go to the ratio); "": chosen at the first group
        self.mode = budget.group_mode or ""
        self.borders: list[float] = []  # z (mm) where groups meet
        self.mc33_faces = 0
        self.pending: list[Any] = []
        self.pending_faces = 0
        self.pieces: list[tuple[Any, Any, Any]] = []  # device (pos, faces in output ids, quad)
        self.host: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.held = 0  # bytes of ``pieces``
        self.deferred: list[tuple[np.ndarray, np.ndarray]] = []  # (output ids, quadric shares) of shared vertices
        self.n_out = 0
        self.top_ids = np.zeros(0, np.int64)  # MC33 ids of the last group's pinned top vertices, sorted
        self.top_out = np.zeros(0, np.int64)  # their output ids
        self.top_pos = np.zeros((0, 3), np.float32)  # and positions
        self.groups: list[dict[str, Any]] = []
        self.seconds = 0.0
        self.timings = {"prepare": 0.0, "decimate": 0.0, "number": 0.0, "spill": 0.0}

    @property
    def cap(self) -> int:
        """Faces a group may have now (its decimation beside the groups held on the device)."""
        return max((self.mesh_room - self.held) // self.per_face, 1)

    @property
    def carries_quadrics(self) -> bool:
        """Whether the groups' quadrics go on to a last pass (in "seams" mode the seams are decimated with quadrics
        of their current faces)."""
        return self.mode == "last pass"

    def first_group_mode(self, mc33_faces: int, z_top: int) -> str:
        """The groups' finish, chosen from the first group (its ``mc33_faces`` up to plane ``z_top``): "last pass"
        where the decimated groups, extrapolated to the whole volume, fit for one last pass, else "seams"."""
        expected = self.ratio * mc33_faces * (self.nz - 1) / max(z_top, 1)
        return "last pass" if expected * self.per_face <= self.mesh_room else "seams"

    def add(self, part: Any) -> None:
        if self.pending and self.pending_faces + part.nt > self.cap:
            self.flush()
        for p in self.pending:  # a group reads only its top slab's shared plane: the others' are freed
            p.plane_above = None
        part.plane_below = None
        self.pending.append(part)
        self.pending_faces += part.nt

    def flush(self) -> None:
        """Decimate the pending slabs as one group, pinned where they meet the slabs below and above: the phases
        gather (``gather_group``), decimate (``decimate_group``), number (``_number``) and spill."""
        if not self.pending:
            return
        t0 = time.perf_counter()
        parts, self.pending, n_faces = self.pending, [], self.pending_faces
        self.pending_faces = 0
        self.mc33_faces += n_faces
        if not self.mode:
            self.mode = self.first_group_mode(self.mc33_faces, parts[-1].z_top)
        group = gather_group(parts, n_faces, self.top_ids, self.top_pos, self.dev)
        del parts  # the slabs' meshes: freed before the decimation
        t1 = self._lap("prepare", t0)
        ratio = min(1.0, self.ratio * (self.slack if self.mode == "last pass" else SEAM_SLACK))
        res = decimate_group(group, max(round(ratio * n_faces), 1), self.origin, self.dev)
        t1 = self._lap("decimate", t1)
        self._number(res, group.nf, group.tid, group.v0)
        self._lap("number", t1)
        pinned = group.nf + len(group.tid)
        self.groups.append(
            {"faces_in": n_faces, "faces_out": len(res.faces), "passes": res.stats.passes, "pinned": pinned}
        )
        if self.held > self.spill_bytes:
            t1 = time.perf_counter()
            self.spill()
            self._lap("spill", t1)
        self.seconds += time.perf_counter() - t0

    def _number(self, res: Any, nf: int, tid: np.ndarray, v0: int) -> None:
        """Number the group's output after the groups before it. Its first ``nf`` vertices are the shared ones below
        (pinned, so all kept, in order); its own vertices get new ids."""
        be = get_backend(self.dev)
        kept = be.to_host(res.kept)  # sync point: 4 bytes per vertex
        if nf and not np.array_equal(kept[:nf], np.arange(nf)):
            raise RuntimeError("a pinned vertex was removed by the decimation of a group of slabs")
        carry = self.carries_quadrics
        if nf and carry:
            self.deferred.append((self.top_out, be.to_host(res.quad, nf).reshape(-1, 10)))
        foreign_out = be.from_host(self.top_out.astype(np.int32) if nf else np.zeros(1, np.int32))
        base = self.n_out - nf
        be.launch(K.GLOBALIZE_FACES, len(res.faces), [res.faces, int(nf), foreign_out, int(base)])
        top_res = np.searchsorted(kept, tid - v0 + nf)  # the pinned top vertices' rows in the output
        self.top_ids, self.top_out = tid, top_res + base
        self.top_pos = be.to_host(res.pos)[top_res] if len(top_res) else np.zeros((0, 3), np.float32)
        if len(top_res):
            self.borders.append(float(np.median(self.top_pos[:, 0])))
        n_new = len(kept) - nf
        n_res = len(res.pos)
        quad = be.view(res.quad, nf, n_res) if carry else None
        self.pieces.append((be.view(res.pos, nf, n_res), res.faces, quad))
        self.held += n_new * (12 + (80 if carry else 0)) + len(res.faces) * 12
        self.n_out += n_new

    def spill(self) -> None:
        """The decimated groups held on the device go to the host."""
        be = get_backend(self.dev)
        for pos, faces, quad in self.pieces:
            q = be.to_host(quad).reshape(-1, 10) if quad is not None else np.zeros((0, 10))
            self.host.append((be.to_host(pos).reshape(-1, 3), be.to_host(faces).reshape(-1, 3), q))
        self.pieces, self.held = [], 0

    def result(self) -> tuple[HostMesh | None, tuple[Any, Any, Any] | None]:
        """``(host mesh, None)`` when groups were spilled, else ``(None, (pos, faces, quad))`` on the device."""
        self.flush()
        ids = np.concatenate([d[0] for d in self.deferred]) if self.deferred else np.zeros(0, np.int64)
        shares = np.concatenate([d[1] for d in self.deferred]) if self.deferred else np.zeros((0, 10))
        if self.host:
            self.spill()
            return join_on_host(self.host, ids, shares, self.origin), None
        pieces, self.pieces = self.pieces, []
        return None, join_on_device(pieces, self.n_out, self.carries_quadrics, ids, shares, self.dev)

    def _lap(self, name: str, t: float) -> float:
        now = time.perf_counter()
        self.timings[name] += now - t
        return now


@dataclass
class Group:
    """A group of slabs gathered for its decimation, on the device: positions (the shared vertices below first,
    ``nf`` of them, then the group's own, MC33 ids ``v0`` ..) and faces in that local numbering, the pinned vertices
    (``lock``: those below and the group's top vertices ``tid``, shared with the slab above)."""

    pos: Any
    faces: Any
    lock: np.ndarray
    nf: int
    tid: np.ndarray
    v0: int


def gather_group(parts: list[Any], n_faces: int, top_ids: np.ndarray, top_pos: np.ndarray, dev: Any) -> Group:
    """The slab meshes ``parts`` (``engine.isosurface.slabs.SlabMesh``) as one group on ``dev``, after the vertices
    it shares with the group below (``top_ids``, their MC33 ids, and ``top_pos``); one sync point (the top slab's
    shared plane)."""
    be = get_backend(dev)
    v0 = parts[0].vstart
    fid = top_ids  # the shared vertices below are the last group's top ones
    nf, n_own = len(fid), sum(p.nv for p in parts)
    above = backend_of(parts[-1].plane_above).to_host(parts[-1].plane_above)  # sync point: 8 bytes per plane edge
    shared = np.zeros(n_own, bool)  # (a mark per vertex: np.unique sorted the plane, 5 ms a group on the H100)
    shared[above[above >= v0] - v0] = True
    tid = np.flatnonzero(shared) + v0
    pos = be.empty(nf + n_own, VEC3F)
    faces = be.empty(n_faces, VEC3I)
    if nf:
        be.upload(pos, np.asarray(top_pos, np.float32))
    ov, of = nf, 0
    for p in parts:
        be.copy(pos, p.verts, dst_offset=ov, count=p.nv)
        be.copy(faces, p.faces, dst_offset=of, count=p.nt)
        ov, of = ov + p.nv, of + p.nt
    fmin = int(fid[0]) if nf else v0
    fmap = np.full(max(v0 - fmin, 1), -1, np.int32)
    fmap[fid - fmin] = np.arange(nf, dtype=np.int32)
    be.launch(K.LOCALIZE_FACES, n_faces, [faces, int(v0), nf, fmin, be.from_host(fmap)])
    lock = np.zeros(nf + n_own, np.int32)
    lock[:nf] = 1
    lock[tid - v0 + nf] = 1
    return Group(pos, faces, lock, nf, tid, v0)


def decimate_group(group: Group, goal: int, origin: np.ndarray, dev: Any) -> Any:
    """A gathered group decimated toward ``goal`` faces with its shared vertices pinned, its quadrics about
    ``origin`` carried out (``engine.decimation.passes.Decimated``); the group's mesh is let go."""
    from engine.decimation.passes import decimate_carrying

    be = get_backend(dev)
    locked = be.from_host(group.lock)
    res = decimate_carrying(group.pos, group.faces, goal, locked=locked, origin=origin, stop_tolerance=PIECE_TOLERANCE)
    group.pos = group.faces = None
    return res


def join_on_host(
    host: list[tuple[np.ndarray, np.ndarray, np.ndarray]], ids: np.ndarray, shares: np.ndarray, origin: np.ndarray
) -> HostMesh:
    """The groups spilled to the host as one mesh, each shared vertex given the other side's share of its quadric
    (``ids``, ``shares``). ``host`` is emptied as it is joined (a group's arrays are let go of once copied), so the
    join holds the groups once, not twice."""
    n_v, n_f, n_q = (sum(len(h[i]) for h in host) for i in range(3))
    pos, faces, quad = np.empty((n_v, 3), np.float32), np.empty((n_f, 3), np.int32), np.empty((n_q, 10))
    ov = of = oq = 0
    while host:
        p, f, q = host.pop(0)
        pos[ov : ov + len(p)], faces[of : of + len(f)], quad[oq : oq + len(q)] = p, f, q
        ov, of, oq = ov + len(p), of + len(f), oq + len(q)
        del p, f, q
    if len(quad):
        quad[ids] += shares  # each side's faces' share of a shared vertex's quadric
    return HostMesh(pos, faces, quad, origin)


def join_on_device(
    pieces: list[tuple[Any, Any, Any]], n_out: int, carried: bool, ids: np.ndarray, shares: np.ndarray, dev: Any
) -> tuple[Any, Any, Any]:
    """The groups held on the device as one mesh ``(pos, faces, quad)`` (``quad`` where ``carried``, each shared
    vertex given the other side's share); ``pieces`` is emptied as it is joined."""
    be = get_backend(dev)
    pos = be.empty(n_out, VEC3F)
    quad = be.empty(n_out, VEC10D) if carried else None
    faces = be.empty(sum(len(p[1]) for p in pieces), VEC3I)
    ov = of = 0
    for p, f, q in pieces:
        be.copy(pos, p, dst_offset=ov, count=len(p))
        if quad is not None:
            be.copy(quad, q, dst_offset=ov)
        be.copy(faces, f, dst_offset=of, count=len(f))
        ov, of = ov + len(p), of + len(f)
    pieces.clear()
    if len(ids) and quad is not None:
        add = [be.from_host(ids.astype(np.int32)), be.from_host(shares, VEC10D), quad]
        be.launch(K.ADD_QUADRICS, len(ids), add)
    return pos, faces, quad


def _host_device(device: Any) -> Backend:
    """The backend a mesh on the host is finished on: ``device``'s, else Warp's current device."""
    if device is not None:
        return get_backend(device)
    import warp as wp

    return get_backend(wp.get_device())


def finish_groups(
    host: HostMesh | None,
    pieces: list[Any] | None,
    origin: np.ndarray,
    target: int,
    budget: Budget,
    borders: list[float],
    seam_mm: float,
    device: Any = None,
) -> tuple[Any, Any, dict[str, Any]]:
    """Finish a decimation begun in groups of slabs (``engine.isosurface.stream``): one last pass on the device where
    they are and fit; otherwise across the ``borders`` (a seam pass on the faces within ``seam_mm`` of them),
    then tiled rounds if still needed, all within ``budget``. ``pieces``: ``[pos, faces, quad]`` on the device,
    emptied (the finish owns the mesh from here, so that no earlier version of it outlives its replacement).
    ``device``: where a mesh spilled to the host is finished (default: Warp's current device)."""
    t0 = time.perf_counter()
    info: dict[str, Any] = {"tiled": True, "rounds": []}
    if pieces is None and host is not None and borders and seams_fit_beside(len(host.pos), len(host.faces), budget):
        # groups spilled to the host while the volume streamed, but the joined mesh fits the device seam pass: it
        # goes back up (with its quadrics where the last pass fits too)
        be = _host_device(device)
        carry = len(host.quad) == len(host.pos) and budget.last_pass_fits(len(host.faces))
        quad = be.from_host(host.quad, VEC10D) if carry else None
        pieces = [be.from_host(host.pos, VEC3F), be.from_host(host.faces, VEC3I), quad]
        info["uploaded"] = {"faces": len(host.faces), "why": "the spilled groups fit the device seam pass"}
        host.release()  # on the device now: the caller's reference holds nothing
        host = None
    if pieces is not None:
        pos, faces, quad = pieces
        pieces.clear()  # the caller's list: from here these names alone hold the mesh, so it is freed when replaced
        if budget.last_pass_fits(len(faces)):
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
        dev = backend_of(pos)
        q = dev.to_host(quad).reshape(-1, 10) if quad is not None else np.zeros((0, 10))
        host = HostMesh(dev.to_host(pos).reshape(-1, 3), dev.to_host(faces).reshape(-1, 3), q, origin)
        del pos, faces, quad, pieces
    else:
        dev = _host_device(device)
    assert host is not None
    if borders and len(host.faces) > target:
        host, info["seams"] = seam_pass(host, borders, seam_mm, target, budget, dev)
    pos, faces, more = finish_host(host, target, budget, dev)
    more["rounds"] = more.get("rounds", [])
    info.update(more)
    info["seconds"] = time.perf_counter() - t0
    return pos, faces, info
