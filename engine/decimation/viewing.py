"""The phone and AR copies of a model (``viewing_copies``), made on the device from the print model: guarded
decimation where the topology can be kept within the budget, else clustering (``engine.decimation.cluster``); the AR
copy continues from the phone copy, or is clustered from the same mesh when the phone copy had to be.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from engine.backend.base import Backend
from engine.backend.select import backend_of, get_backend
from engine.budget import Budget, BudgetSpec

if TYPE_CHECKING:
    from engine.report import ExportInfo

SPECK_FACES = 4  # a closed piece keeps at least a tetrahedron under the topology guard
FACES_PER_PIECE = 200  # when pieces must go, a viewing copy keeps about this many faces per piece
HOPELESS = 2  # a copy whose topology needs this many times its budget is clustered at once
VIEW_MAX_PASSES = 100  # decimation passes per round of a viewing copy (the print model has no such limit)
STALL_PASSES = 10  # a round's last passes that tell whether another round could meet the budget


@dataclass
class ViewingCopy:
    """A viewing copy on the device (``pos``, ``faces``) and its report entry (``summary``: the report's
    ``exports["phone.glb" | "ar.glb"]``, ``engine.report.ExportInfo``), with what a smaller
    copy made from it needs: its piece count when known, whether it is closed (watertight and 2-manifold), and
    where it was clustered, the prepared mesh it was clustered from (``engine.decimation.cluster.Clustering``)."""

    pos: Any
    faces: Any
    summary: ExportInfo
    pieces: int | None = None
    closed: bool = False
    clustering: Any = None


def _stalled(stats: Any, excess: int) -> bool:
    """Whether another round of decimation would barely help: the guards stopped it before its pass limit, or its
    last passes' collapses (two faces each), kept up for a whole round, would not remove ``excess`` faces."""
    if stats.passes < VIEW_MAX_PASSES:
        return True
    tail = stats.collapses[-STALL_PASSES:]
    return 2 * sum(tail) * VIEW_MAX_PASSES < excess * max(len(tail), 1)


def _backend(device: Any, arr: Any) -> Backend:
    """The backend of ``device`` (a Warp device or spec, ``"opencl[:N]"`` or a ``Backend``), or where ``arr`` is."""
    return backend_of(arr) if device is None else get_backend(device)


def _name(be: Backend) -> str:
    """A device's name in the report (a Warp device's own name, as before the backends)."""
    return str(be.device) if be.kind == "warp" else be.label  # type: ignore[attr-defined]


def _decimate(pos: Any, faces: Any, max_triangles: int, room: Budget, device: Any = None) -> tuple[Any, Any, Any]:
    """``decimate_device`` for a viewing copy on ``device`` (default: where the mesh is; a host mesh is taken there),
    tiled (``engine.decimation.tiles``) where it would not fit ``room``."""
    from engine.decimation.passes import DecimationStats, decimate_device
    from engine.decimation.tiles import decimate_within
    from engine.surface.devmesh import on_device

    be = _backend(device, pos)
    if room.fits_decimation(len(faces)):
        return decimate_device(*on_device(be, pos, faces), max_triangles, max_passes=VIEW_MAX_PASSES)
    pos, faces, _ = decimate_within(pos, faces, max_triangles, room, be, max_passes=VIEW_MAX_PASSES)
    return pos, faces, DecimationStats(output_faces=len(faces), passes=0, stopped="tiled (memory budget)")


def _prepares_within(n_faces: int, room: Budget, moving: bool) -> bool:
    """Whether a mesh's speck removal and piece census (``engine.surface.islands``) fit ``room`` on the device, with
    the mesh itself where it has to be moved there: then its specks go before any decimation (a scan of thousands
    of pieces keeps few of them in a phone copy), which runs tiled where it would not fit."""
    per_face = room.costs.islands + (room.costs.mesh if moving else 0)
    return room.fits(n_faces * per_face)


def _take_to(pos: Any, faces: Any, max_triangles: int, room: Budget, device: Any) -> tuple[Any, Any, dict[str, Any]]:
    """A mesh taken to ``device`` for its viewing copies (their speck removal, censuses, decimation and clustering
    run there, not on Warp's one CPU thread): as it is where its speck removal fits ``room``, else first decimated
    in tiles on the device (``engine.decimation.tiles``, every guard kept, no piece dropped) to what fits."""
    from engine.surface.devmesh import on_device

    be = _backend(device, pos)
    if _prepares_within(len(faces), room, backend_of(pos) is not be):
        return (*on_device(be, pos, faces), {"device": _name(be), "faces": len(faces)})
    n_in = len(faces)
    pos, faces, tiled = _decimated_to_fit(pos, faces, room.costs.decimate, max_triangles, room, be)
    return pos, faces, {"device": _name(be), "faces": len(faces), "tiled_from_faces": n_in, "tiled": tiled}


def _decimated_to_fit(
    pos: Any, faces: Any, per_face: int, max_triangles: int, room: Budget, device: Any
) -> tuple[Any, Any, bool]:
    """A mesh decimated on ``device`` (tiled where that does not fit ``room``: ``engine.decimation.tiles``, every guard
    kept, no piece dropped) toward the faces of which work needing ``per_face`` bytes each fits ``room``, but not
    below ``max_triangles``; ``(pos, faces, tiled)``."""
    from engine.decimation.tiles import decimate_within

    fitting = max(room.share(1) // per_face, max_triangles)
    be = _backend(device, pos)
    pos, faces, info = decimate_within(pos, faces, fitting, room, be, max_passes=VIEW_MAX_PASSES)
    return pos, faces, bool(info.get("tiled"))


def _make_copy(
    pos: Any,
    faces: Any,
    max_triangles: int,
    pieces: int | None,
    closed: bool,
    room: Budget | None = None,
    device: Any = None,
) -> ViewingCopy:
    """One viewing copy (see ``viewing_copy``), its decimation on ``device`` within ``room`` (default: none)."""
    room = room or Budget()
    if len(faces) <= max_triangles:
        return ViewingCopy(pos, faces, {"faces": len(faces), "decimated": False}, pieces, closed)
    from engine.decimation.cluster import Clustering, piece_census
    from engine.surface.islands import remove_islands_device

    passes = dropped = 0
    keep: int | None = None
    summary: ExportInfo = {"topology_preserved": True}
    moving = device is not None and backend_of(pos) is not get_backend(device)  # e.g. a model laid out on the host
    if moving or not _prepares_within(len(faces), room, moving):
        pos, faces, summary["taken_to"] = _take_to(pos, faces, max_triangles, room, device)

    def drop(n: int) -> None:
        nonlocal pos, faces, dropped, pieces
        pos, faces, isl = remove_islands_device(pos, faces, keep_largest=n)
        dropped, pieces = dropped + int(isl["removed_pieces"]), int(isl["pieces_after"])

    if pieces is not None and pieces * SPECK_FACES > max_triangles:
        keep = max(1, max_triangles // FACES_PER_PIECE)
        drop(keep)
    # a closed mesh of C pieces and Euler characteristic X keeps at least 8 C - 2 X faces under the topology guard
    # (each piece at least 4 + 4 genus): far above the budget, tunnels must close anyway, so cluster at once; and
    # where the largest piece alone (never dropped) needs more than the budget, no round can meet it
    hopeless = closed and (
        (pieces is not None and 8 * pieces - 2 * (len(pos) - len(faces) // 2) > HOPELESS * max_triangles)
        or piece_census(pos, faces).floor(1) > max_triangles
    )
    stats = None
    if not hopeless:
        pos, faces, stats = _decimate(pos, faces, max_triangles, room, device)
        passes += stats.passes
    while stats is not None and len(faces) > max_triangles:
        census = piece_census(pos, faces)
        pieces = len(census)
        if pieces <= 1:
            break
        if _stalled(stats, len(faces) - max_triangles):
            # decimating again would barely help: keep the largest pieces that fit as they are, if any
            if census.fit(max_triangles):
                drop(census.fit(max_triangles))
            break
        keep = (
            max(1, min(pieces // 2, max_triangles // FACES_PER_PIECE))
            if keep is None
            else max(1, min(keep // 2, pieces - 1))
        )
        drop(keep)
        pos, faces, stats = _decimate(pos, faces, max_triangles, room, device)
        passes += stats.passes
    clustering = None
    if len(faces) > max_triangles:  # pieces of high genus: this viewing copy may close tunnels to meet the budget
        if not room.fits(len(faces) * room.costs.cluster):  # first decimated to what fits
            n_in = len(faces)
            pos, faces, _ = _decimated_to_fit(pos, faces, room.costs.cluster, max_triangles, room, None)
            summary["tiled_for_clustering"] = {"faces_in": n_in, "faces": len(faces)}
        clustering = Clustering(pos, faces)
        pos, faces, summary["clustered"] = clustering.copy(max_triangles)
        summary["topology_preserved"] = False
    summary.update(
        {
            "faces": len(faces),
            "decimated": True,
            "passes": passes,
            "pieces_dropped": dropped,
            "over_budget": len(faces) > max_triangles,
        }
    )
    return ViewingCopy(pos, faces, summary, pieces, closed and clustering is None, clustering)


def viewing_copy(
    pos: Any, faces: Any, max_triangles: int, pieces: int | None = None, closed: bool = False
) -> tuple[Any, Any, ExportInfo]:
    """A device copy within ``max_triangles`` faces, decimated on the device; ``(pos, faces, summary)``, the arrays
    themselves when already within budget.

    The copy continues the print model's decimation with every guard. Topology-preserving decimation cannot shrink
    a closed piece below a tetrahedron, so a scan with thousands of specks cannot reach a phone-sized budget: then
    the smallest pieces (by volume) are dropped, halving the number kept, and the rest decimated again, until the
    budget is met (each round works on the already small copy); when the pieces could not fit even as tetrahedra
    (``pieces``, the count when known), they are thinned before the first decimation. When a round stalls (the
    guards stop it, or its last passes collapse too little to matter), the largest pieces that fit as they are
    stay and no round follows. Where pieces of high genus still keep the copy over budget (every tunnel keeps a
    ring of faces), the copy is clustered (``engine.decimation.cluster``: ``topology_preserved`` false, small tunnels
    close). The print model keeps every piece and every guard. A ``closed`` copy whose pieces and Euler
    characteristic need far more faces than the budget under the topology guard, or whose largest piece alone
    needs more, is clustered without decimating first.
    """
    copy = _make_copy(pos, faces, max_triangles, pieces, closed)
    return copy.pos, copy.faces, copy.summary


def viewing_copies(
    pos: Any,
    faces: Any,
    budgets: list[int],
    pieces: int | None = None,
    closed: bool = False,
    room: BudgetSpec = None,
    device: Any = None,
) -> list[tuple[Any, Any, ExportInfo]]:
    """Viewing copies within each of ``budgets`` (largest first: the phone copy, then the AR copy), each made from
    the one before (``viewing_copy``; the first from the print model ``pos``, ``faces`` of ``pieces`` pieces,
    ``closed`` when watertight and 2-manifold), carrying its piece count and closedness.

    Where a copy had to be clustered (its topology could not be kept within its budget), a smaller budget cannot
    keep it either: the next copy is clustered at once from the same mesh (its quadrics and cell-size trials
    reused; ``clustered.input_faces`` says which mesh), rather than decimated from the clustered copy, which the
    guards can barely touch. Its ``pieces_dropped`` counts the pieces dropped beyond the copy before it (none).
    ``room``: the device memory a copy's decimation may use (an ``engine.budget.Budget``, or bytes as
    ``Budget.of`` reads them; None: no limit); ``device``: where the copies are decimated (default: where ``pos``
    is; a print model laid out on the host is decimated on the GPU).
    """
    room = Budget.of(room)
    out: list[tuple[Any, Any, ExportInfo]] = []
    prev: ViewingCopy | None = None
    for most in budgets:
        if prev is None:
            copy = _make_copy(pos, faces, most, pieces, closed, room, device)
        elif len(prev.faces) <= most:
            copy = ViewingCopy(prev.pos, prev.faces, {"faces": len(prev.faces), "decimated": False}, prev.pieces)
            copy.closed, copy.clustering = prev.closed, prev.clustering
        elif prev.clustering is not None:
            cpos, cfaces, info = prev.clustering.copy(most)
            summary: ExportInfo = {"topology_preserved": False, "clustered": info, "faces": len(cfaces)}
            summary.update({"decimated": True, "passes": 0, "pieces_dropped": 0, "over_budget": len(cfaces) > most})
            copy = ViewingCopy(cpos, cfaces, summary, None, False, prev.clustering)
        else:
            copy = _make_copy(prev.pos, prev.faces, most, prev.pieces, prev.closed, room, device)
        out.append((copy.pos, copy.faces, copy.summary))
        prev = copy
    return out
