"""Where a template piece meets the bone around the hole: its rim, the gap there, and whether the hole goes on.

A template piece is a thin plate; its rim is the outline of the plate seen along its thinnest principal axis. The
plate's voxels are projected on the plane of its two widest axes (one pixel per voxel extent along each axis, so
neighbouring voxels land on neighbouring pixels), the outline's pixels are its rim, and each takes the smallest gap
of the voxels projected onto it: the distance from the voxel to the nearest bone voxel less the two voxels' extent
along the line between them (voxels that share a face or a corner have no gap). Pixels of voxels on the scan's
border are left out (the rim there was not scanned).

``contact``: the share of the rim with a gap of at most ``CONTACT_GAP_VOXELS`` (the template meets the bone there);
``gap_mm``/``gap_voxels``: the mean gap over the rim (no bone within reach counts as the reach); ``open_share``: the
share with a gap of more than ``OPEN_GAP_VOXELS`` or no bone within reach. ``thickness_mm``: the piece's volume over
its outline's area (a plate's mean thickness; reported, not judged: a bevelled rim thins it). ``opening_width_mm``
(issue 42): the diameter of the largest disc inside that outline, the hole's opening (the smallest defect's
width is judged on it where the shell's reading over-reads a thin shell).

``open_toward_plane`` (its own function): whether the hole goes on past the template toward the symmetry plane,
where the mirror image lacks the bone too (a defect across the midline). ``spans_shell`` (issue 42): whether the
piece is a hole through the whole shell, judged on its columns along the mirrored shell's local normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.defect.grid import touching

CONTACT_GAP_VOXELS = 1.0
MIN_ALONG = 0.5  # a path toward the plane runs along the shell when the plane's direction is 30+ degrees off its normal
OPEN_GAP_VOXELS = 2.0


@dataclass(frozen=True)
class Rim:
    """The rim of one template piece (see the module)."""

    contact: float
    gap_mm: float
    gap_voxels: float
    open_share: float
    open_toward_plane: float
    samples: int
    thickness_mm: float
    thickness_voxels: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "contact_share": round(self.contact, 4),
            "gap_mm": round(self.gap_mm, 4),
            "gap_voxels": round(self.gap_voxels, 4),
            "open_share": round(self.open_share, 4),
            "open_toward_plane": round(self.open_toward_plane, 4),
            "outline_samples": self.samples,
            "thickness_mm": round(self.thickness_mm, 3),
            "thickness_voxels": round(self.thickness_voxels, 3),
        }


NO_RIM = Rim(0.0, float("inf"), float("inf"), 1.0, 1.0, 0, 0.0, 0.0)


def rim_of(
    index: npt.NDArray[np.int64],
    bone: npt.NDArray[np.bool_],
    spacing_zyx: tuple[float, float, float],
    on_border: npt.NDArray[np.bool_],
    reach_mm: float,
) -> Rim:
    """The rim of a template piece (see the module).

    Args:
        index: (N, 3) voxel indices (z, y, x) of the piece in ``bone``'s array.
        bone: the scan's bone (bool), the same array.
        spacing_zyx: voxel size in mm.
        on_border: (N,) the voxel lies on the scan's border.
        reach_mm: how far to look for bone; a gap beyond it is open.
    """
    from scipy import ndimage as ndi
    from scipy.spatial import cKDTree

    if len(index) < 4:
        return NO_RIM
    sp = np.asarray(spacing_zyx, dtype=np.float64)
    pts = index * sp
    # the outline seen along the thinnest axis; each outline pixel takes its voxels' smallest gap, so only the
    # voxels seen on the outline are measured
    img, u1, u2, (h1, h2, h3) = _outline_image(pts, sp)
    thickness = len(index) * float(np.prod(sp)) / (float(img.sum()) * h1 * h2)
    outline = img & ~ndi.binary_erosion(img)
    pix = u1 * img.shape[1] + u2
    seen = np.flatnonzero(outline.ravel()[pix])
    pix, at = pix[seen], pts[seen]
    margin = np.ceil(reach_mm / sp).astype(np.int64) + 1
    lo = np.maximum(index.min(axis=0) - margin, 0)
    hi = np.minimum(index.max(axis=0) + margin + 1, bone.shape)
    near = np.argwhere(bone[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]) + lo
    if len(near) == 0:
        gap_mm = np.full(len(at), np.inf)
        ext = np.full(len(at), sp.min())
    else:
        dist, j = cKDTree(near * sp).query(at, distance_upper_bound=reach_mm + float(sp.max()), workers=1)
        found = np.isfinite(dist)
        u = np.zeros_like(at)
        u[found] = (near[j[found]] * sp - at[found]) / np.maximum(dist[found, None], 1e-12)
        ext = np.where(found, np.abs(u) @ sp, sp.min())  # both voxels' half extents along the line between them
        gap_mm = np.where(found, np.maximum(dist - ext, 0.0), np.inf)
    gap_vox = gap_mm / ext
    voxel = float(np.prod(sp)) ** (1 / 3)  # a gap beyond the reach counts as the reach, in voxels of this size
    order = np.lexsort((gap_vox, pix))  # by pixel, then gap: each pixel's smallest gap first
    first = np.ones(len(order), dtype=bool)
    first[1:] = pix[order][1:] != pix[order][:-1]
    best = order[first]
    best = best[~on_border[seen][best]]
    if len(best) == 0:
        return Rim(0.0, float("inf"), float("inf"), 1.0, 0.0, 0, thickness, thickness / h3)
    g_vox, g_mm = gap_vox[best], gap_mm[best]
    finite = np.isfinite(g_mm)
    return Rim(
        contact=float(np.mean(finite & (g_vox <= CONTACT_GAP_VOXELS))),
        gap_mm=float(np.mean(np.where(finite, g_mm, reach_mm))),
        gap_voxels=float(np.mean(np.where(finite, g_vox, reach_mm / voxel))),
        open_share=float(np.mean(~finite | (g_vox > OPEN_GAP_VOXELS))),
        open_toward_plane=0.0,
        samples=len(best),
        thickness_mm=thickness,
        thickness_voxels=thickness / h3,
    )


def _outline_image(pts: npt.NDArray[np.float64], sp: npt.NDArray[np.float64]) -> tuple[Any, Any, Any, Any]:
    """A piece's voxels (grid mm ``pts``) seen along its thinnest principal axis: the filled picture on the plane of
    its two widest axes (a pixel per voxel extent along each), each voxel's pixel (``u1``, ``u2``) and the pixels'
    extents with the voxels' extent along the thinnest axis (``h1``, ``h2``, ``h3`` mm)."""
    from scipy import ndimage as ndi

    centre = pts.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((pts - centre).T))
    e1, e2, e3 = axes[:, 2], axes[:, 1], axes[:, 0]
    h1, h2, h3 = float(np.abs(e1) @ sp), float(np.abs(e2) @ sp), float(np.abs(e3) @ sp)
    u1 = np.round((pts - centre) @ e1 / h1).astype(np.int64)
    u2 = np.round((pts - centre) @ e2 / h2).astype(np.int64)
    u1 -= u1.min() - 1
    u2 -= u2.min() - 1
    img = np.zeros((int(u1.max()) + 2, int(u2.max()) + 2), dtype=bool)
    img[u1, u2] = True
    return ndi.binary_fill_holes(img), u1, u2, (h1, h2, h3)


def opening_width_mm(index: npt.NDArray[np.int64], spacing_zyx: tuple[float, float, float]) -> float:
    """How wide a piece's opening is (mm): the diameter of the largest disc inside its outline seen along its
    thinnest principal axis (``rim_of``'s picture): twice the largest distance from a pixel's centre to the nearest
    pixel centre outside, less the larger pixel extent (the outline's edge lies between its last pixel centre and
    the first outside, so the centres' distance over-reads the diameter by half a pixel at each side). A hole's plug
    is as wide as its opening, however thin the shell."""
    from scipy import ndimage as ndi

    if len(index) < 4:
        return 0.0
    sp = np.asarray(spacing_zyx, dtype=np.float64)
    img, _, _, (h1, h2, _) = _outline_image(index * sp, sp)
    return 2.0 * float(ndi.distance_transform_edt(img, sampling=(h1, h2)).max()) - max(h1, h2)


def open_toward_plane(
    index: npt.NDArray[np.int64],
    bone: npt.NDArray[np.bool_],
    mirrored: npt.NDArray[np.float32],
    spacing_zyx: tuple[float, float, float],
    side_mm: npt.NDArray[np.float64],
    plane_normal_zyx: npt.NDArray[np.float64],
    reach_mm: float,
) -> float:
    """Whether the hole goes on past the template toward the symmetry plane. From every voxel of the piece a path
    goes toward the plane along the shell (the way to the plane less its part along the shell's normal: the main
    axis of the mirrored scan's gradients over the piece), through the piece and on out of it, up to ``reach_mm``
    (or the plane) past its edge; returns the share of the paths that meet no bone (within a voxel of the path).
    Where the shell faces the plane (a side wall) the way to the plane goes through it: those paths tell nothing
    and are left out. A one-sided defect's paths meet its rim; a defect across the midline's meet none there (the
    mirror image lacks that bone too)."""

    sp = np.asarray(spacing_zyx, dtype=np.float64)
    margin = np.ceil(reach_mm / sp).astype(np.int64) + 2
    lo = np.maximum(index.min(axis=0) - margin, 0)
    hi = np.minimum(index.max(axis=0) + margin + 1, bone.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    shape = np.asarray(tuple(int(b - a) for a, b in zip(lo, hi, strict=True)))
    local = index - lo
    piece = np.zeros(tuple(shape), dtype=bool)
    piece[tuple(local.T)] = True
    near_bone = touching(bone[box])
    # the shell's normal: the main axis of the mirrored scan's gradients over the piece (their structure tensor)
    grads = np.gradient(mirrored[box].astype(np.float64), *sp)
    g = np.stack([np.asarray(gr)[tuple(local.T)] for gr in grads], axis=1)
    _, axes = np.linalg.eigh(g.T @ g)
    nu = np.broadcast_to(axes[:, 2], (len(index), 3))
    toward = -np.sign(side_mm)[:, None] * np.asarray(plane_normal_zyx)[None, :]
    tangent = toward - np.einsum("ij,ij->i", toward, nu)[:, None] * nu
    along = np.linalg.norm(tangent, axis=1)
    tangent /= np.maximum(along[:, None], 1e-12)
    # where the shell faces the plane (a side wall), the way to the plane goes through the shell, not along it: no
    # path there tells whether the hole goes on toward the midline
    keep = along >= MIN_ALONG
    if not keep.any():
        return 0.0
    local, tangent, side_mm = local[keep], tangent[keep], side_mm[keep]
    # every voxel of the piece walks toward the plane along the shell: through the piece, then out of it up to the
    # reach (or the plane); its path meets the bone of the hole's rim, or nothing
    step = 0.5 * float(sp.min())
    start, tan = local, tangent
    limit = np.minimum(np.abs(side_mm), reach_mm)
    out_at = np.full(len(start), np.inf)  # the path's length when it left the piece
    met = np.zeros(len(start), dtype=bool)
    done = np.zeros(len(start), dtype=bool)
    k = 0
    while not done.all():
        k += 1
        live = np.flatnonzero(~done)
        pos = np.round(start[live] + k * step * tan[live] / sp).astype(np.int64)
        ok = np.all((pos >= 0) & (pos < shape), axis=1)
        in_piece = np.zeros(len(pos), dtype=bool)
        in_piece[ok] = piece[tuple(pos[ok].T)]
        hit = np.zeros(len(pos), dtype=bool)
        hit[ok] = near_bone[tuple(pos[ok].T)]
        left = ~in_piece & ~np.isfinite(out_at[live])
        out_at[live[left]] = k * step
        hit &= np.isfinite(out_at[live])  # only once out of the piece: its own partial-volume rim is not the rim
        met[live[hit]] = True
        beyond = np.isfinite(out_at[live]) & (k * step - out_at[live] >= limit[live])
        done[live[hit | ~ok | beyond]] = True
        done[live[k * step > np.abs(side_mm[live]) + reach_mm]] = True
    return float(np.mean(~met))


SPAN_MISSING = 0.75  # a column spans the shell when the scan lacks at least this share of the mirrored shell on it
TRUNCATE = 4.0  # the structure tensor's Gaussian reaches this many sigmas (scipy's default)
TENSOR_SIGMA_MM = 2.0  # the shell's local normal: the structure tensor of the mirrored scan, smoothed this much


@dataclass(frozen=True)
class Span:
    """Whether a piece goes through the whole shell (``spans_shell``): ``area_mm2`` of its outline (seen along its
    thinnest axis) where its columns along the shell's local normal span the mirrored shell, ``share`` that area
    over the outline's, ``missing``: the median share of the mirrored shell the scan lacks on the piece's columns.
    ``spans``: per voxel of the piece, whether its column spans the shell; ``column_missing``: per voxel, the share
    of the mirrored shell the scan lacks on its column (neither in ``to_dict``)."""

    area_mm2: float
    share: float
    missing: float
    spans: npt.NDArray[np.bool_] | None = field(default=None, repr=False, compare=False)
    column_missing: npt.NDArray[np.float64] | None = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict[str, Any]:
        return {"area_mm2": round(self.area_mm2, 2), "share": round(self.share, 4), "missing": round(self.missing, 4)}


def _local_normals(field: npt.NDArray[Any], at: npt.NDArray[np.int64], sp: npt.NDArray[np.float64]) -> Any:
    """Unit normals (z, y, x) of a shell at voxels ``at`` of ``field`` (a box of the mirrored scan): the main axis
    of the field's gradients' structure tensor, smoothed over ``TENSOR_SIGMA_MM`` (the middle of a shell, where
    the gradient vanishes, takes its faces' direction)."""
    from scipy import ndimage as ndi

    from engine.io.parallel import decode_threads, ordered_map

    sigma = TENSOR_SIGMA_MM / sp
    # only the box the smoothing reaches from ``at`` matters (the filters' radius, and a voxel more for the
    # gradient's central differences): the same values as over the whole field, on less of it
    reach = np.array([int(TRUNCATE * s + 0.5) for s in sigma]) + 1
    lo = np.maximum(at.min(axis=0) - reach, 0)
    hi = np.minimum(at.max(axis=0) + reach + 1, field.shape)
    field = field[tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))]
    at = at - lo
    grads = np.gradient(field.astype(np.float32), *sp)
    pairs = [(i, j) for i in range(3) for j in range(i, 3)]
    where = tuple(at.T)

    def smoothed(ij: tuple[int, int]) -> Any:
        return ndi.gaussian_filter(grads[ij[0]] * grads[ij[1]], sigma, mode="nearest", truncate=TRUNCATE)[where]

    # the tensor's six products smoothed side by side (scipy's filters release the GIL: a piece's span is the
    # judge's longest measure)
    tensor = np.empty((len(at), 3, 3))
    for (i, j), t in zip(pairs, ordered_map(smoothed, pairs, min(len(pairs), decode_threads())), strict=True):
        tensor[:, i, j] = tensor[:, j, i] = t
    _, vecs = np.linalg.eigh(tensor)
    return vecs[:, :, 2]


def spans_shell(
    index: npt.NDArray[np.int64],
    bone: npt.NDArray[np.bool_],
    mirrored: npt.NDArray[Any],
    level: float,
    spacing_zyx: tuple[float, float, float],
    reach_mm: float,
) -> Span:
    """Whether a piece (voxels ``index`` of the mirrored skull missing from the scan) is a hole through the shell:
    from each of its voxels a column runs along the mirrored shell's local normal over the run of mirrored bone
    (``mirrored`` at or above ``level``, gaps under a voxel bridged) it lies in, up to ``reach_mm`` either way; the
    column spans the shell when the scan (``bone``) lacks at least ``SPAN_MISSING`` of it. A hole through the shell
    spans it over its opening however its rim is bevelled; a sliver of asymmetry or a partial-thickness dent has
    the scan's bone across the rest of the shell on every column."""
    from scipy import ndimage as ndi

    if len(index) < 4:
        return Span(0.0, 0.0, 0.0)
    sp = np.asarray(spacing_zyx, dtype=np.float64)
    margin = np.ceil((reach_mm + 3.0 * TENSOR_SIGMA_MM) / sp).astype(np.int64) + 1
    lo = np.maximum(index.min(axis=0) - margin, 0)
    hi = np.minimum(index.max(axis=0) + margin + 1, bone.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    m_box = np.asarray(mirrored[box])
    mirror = m_box >= level
    b_box = np.asarray(bone[box])
    local = index - lo
    nu = _local_normals(m_box, local, sp)
    step = 0.5 * float(sp.min())
    offs = np.arange(-reach_mm, reach_mm + 0.5 * step, step)
    c = int(np.argmin(np.abs(offs)))
    pos = np.round(local[:, None, :] + offs[None, :, None] * nu[:, None, :] / sp).astype(np.int64)
    shape = np.asarray(m_box.shape)
    ok = np.all((pos >= 0) & (pos < shape), axis=2)
    pos = np.clip(pos, 0, shape - 1)
    at = (pos[..., 0] * shape[1] + pos[..., 1]) * shape[2] + pos[..., 2]  # flat indices in the box
    m = mirror.reshape(-1)[at] & ok
    b = np.ascontiguousarray(b_box).reshape(-1)[at] & ok
    gap = max(1, int(np.ceil(float(sp.max()) / step)))
    closed = ndi.binary_closing(m, structure=np.ones((1, 2 * gap + 1), dtype=bool), border_value=0) | m
    closed[:, c] = True
    run = np.zeros_like(closed)
    run[:, c:] = np.cumprod(closed[:, c:], axis=1).astype(bool)
    run[:, : c + 1] |= np.cumprod(closed[:, c::-1], axis=1)[:, ::-1].astype(bool)
    in_shell = run & m
    missing = (in_shell & ~b).sum(axis=1) / np.maximum(in_shell.sum(axis=1), 1)
    spans = missing >= SPAN_MISSING
    # the outline seen along the piece's thinnest axis, and the part of it whose columns span the shell
    img, u1, u2, (h1, h2, _) = _outline_image(index * sp, sp)
    span_img = np.zeros_like(img)
    span_img[u1[spans], u2[spans]] = True
    outline = float(img.sum())
    return Span(
        area_mm2=float(span_img.sum()) * h1 * h2,
        share=float(span_img.sum()) / max(outline, 1.0),
        missing=float(np.median(missing)),
        spans=spans,
        column_missing=missing,
    )


@dataclass(frozen=True)
class Across:
    """How far the hole around a piece goes on past the symmetry plane (``past_plane``), where the mirror image
    lacks the bone too. ``past_mm``: the hole reaches this far past the plane (+: on the plane's other side; a
    negative value: its rim lies this far short of the plane) over a front at least ``front_mm`` wide; ``rows``:
    the paths measured, ``open_rows``: those that met no bone before ``reach_mm`` past the plane; ``voxel_mm``: a
    voxel's extent along the paths (their median), the measure's own step."""

    past_mm: float
    front_mm: float
    rows: int
    open_rows: int
    reach_mm: float
    voxel_mm: float

    def to_dict(self) -> dict[str, Any]:
        return {"past_plane_mm": round(self.past_mm, 2), "front_mm": round(self.front_mm, 2), "paths": self.rows,
                "open_paths": self.open_rows, "reach_mm": round(self.reach_mm, 2),
                "voxel_along_mm": round(self.voxel_mm, 3)}  # fmt: skip


def _plate_normals(pts: npt.NDArray[np.float64], at: npt.NDArray[np.float64], radius_mm: float) -> Any:
    """A plate's normals (unit, z, y, x) at points ``at`` (mm): the thinnest principal axis of the plate's points
    ``pts`` (mm) within ``radius_mm`` of each (of all of them where fewer than four are). The piece's own shape,
    not the mirrored scan's gradients: at a piece's edge the mirror's own hole (past the plane, the mirror lacks
    the bone too) turns those toward the plane."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    out = np.empty((len(at), 3))
    for i, near in enumerate(tree.query_ball_point(at, radius_mm, workers=1)):
        q = pts[near] if len(near) >= 4 else pts
        _, axes = np.linalg.eigh(np.cov((q - q.mean(axis=0)).T))
        out[i] = axes[:, 0]
    return out


def past_plane(
    index: npt.NDArray[np.int64],
    bone: npt.NDArray[np.bool_],
    spacing_zyx: tuple[float, float, float],
    side_mm: npt.NDArray[np.float64],
    plane_normal_zyx: npt.NDArray[np.float64],
    reach_mm: float,
    tube_mm: float,
    front_mm: float,
    normal_mm: float,
    near_mm: float,
) -> Across | None:
    """How far the hole that a piece fills goes on past the symmetry plane: where the scan lacks the bone on both
    sides of it, and the mirror image too (past the plane the mirror image is this side's missing bone).

    The piece is cut into rows across the way to the plane (the plane's direction less its part along the shell's
    normal over the piece, the rows one voxel extent apart across it). From each row's voxel nearest the plane a
    path runs along the shell toward the plane (its direction less its part along the piece's local normal there:
    the thinnest axis of its voxels within ``normal_mm``, ``_plate_normals``) until it meets the scan's bone within
    ``tube_mm`` of it along that normal: the hole's rim on that row. A one-sided defect's rows meet their rim at
    once, short of the plane; a hole across the midline's rows facing it meet its rim past the plane, as far past
    it as the hole goes (the template stops as far short of the plane: the mirror image lacks that bone too).
    Returns the hole's reach past the plane (mm; + past it, - the rim that far short of it) over a front
    ``front_mm`` wide: the smallest of the rows' largest reaches that make that width (one row's is noise). A row
    meeting no bone up to ``reach_mm`` past the plane counts as ``reach_mm``; one that leaves the scan first, whose
    shell faces the plane (a side wall: the way to the plane runs through the shell, not along it) or that starts
    more than ``near_mm`` from the plane is left out. None when no row is measured.

    Args:
        index: (N, 3) voxel indices (z, y, x) of the piece in ``bone``'s and ``mirrored``'s arrays.
        bone: the scan's bone (bool).
        spacing_zyx: voxel size in mm.
        side_mm: (N,) the piece's voxels' signed distances to the plane (mm).
        plane_normal_zyx: the plane's unit normal (z, y, x).
        reach_mm: how far past the plane a row looks for bone.
        tube_mm: bone this far from a path along the shell's normal is met (the shell curves away from a straight
            path: half the shell's thickness or so).
        front_mm: the width of the front whose reach is returned.
        normal_mm: the piece's local normal is that of its voxels within this distance.
        near_mm: rows whose voxel nearest the plane lies farther from it are left out: a straight path that long
            leaves the skull's curved shell and meets no bone, whatever the hole (the gantry-tilt head's one-sided
            cuts 61 mm off the plane, low at the side, read 15 mm past it).
    """
    if len(index) < 4:
        return None
    sp = np.asarray(spacing_zyx, dtype=np.float64)
    n = np.asarray(plane_normal_zyx, dtype=np.float64)
    pts = index * sp
    sgn = 1.0 if float(np.median(side_mm)) > 0 else -1.0
    toward = -sgn * n
    nu = _plate_normals(pts, pts.mean(axis=0)[None, :], float("inf"))[0]
    across = np.cross(nu, toward)  # the rows run across the way to the plane
    if float(np.linalg.norm(across)) < 1e-6:
        return None
    across /= float(np.linalg.norm(across))
    h2 = float(np.abs(across) @ sp)
    row = np.round((pts - pts.mean(axis=0)) @ across / h2).astype(np.int64)
    past_v = -sgn * np.asarray(side_mm, dtype=np.float64)
    order = np.lexsort((-past_v, row))  # by row, the voxel nearest the plane first
    first = np.ones(len(order), dtype=bool)
    first[1:] = row[order][1:] != row[order][:-1]
    ends = index[order[first]]
    past_e = past_v[order[first]]
    near = past_e >= -near_mm
    if not near.any():
        return None
    ends, past_e = ends[near], past_e[near]
    nus = _plate_normals(pts, ends * sp, normal_mm)
    tan = toward[None, :] - (nus @ toward)[:, None] * nus
    along = np.linalg.norm(tan, axis=1)
    ok = along >= MIN_ALONG
    if not ok.any():
        return None
    ends, past_e, nus, tan, along = ends[ok], past_e[ok], nus[ok], tan[ok] / along[ok, None], along[ok]
    step = 0.5 * float(sp.min())
    depth = np.arange(-tube_mm, tube_mm + 0.5 * step, step)
    shape = np.asarray(bone.shape)
    past = np.full(len(ends), np.nan)  # nan: not known yet
    met = np.zeros(len(ends), dtype=bool)
    k = 0
    live = np.arange(len(ends))
    while len(live):
        here = past_e[live] + along[live] * k * step  # each path's reach past the plane at this step
        pos = (ends[live] * sp + (k * step) * tan[live])[:, None, :] + depth[None, :, None] * nus[live][:, None, :]
        vox = np.round(pos / sp).astype(np.int64)
        inside = np.all((vox >= 0) & (vox < shape), axis=2)
        vox = np.clip(vox, 0, shape - 1)
        hit = (bone[vox[..., 0], vox[..., 1], vox[..., 2]] & inside).any(axis=1)
        gone = ~inside[:, len(depth) // 2]  # the path itself left the scan
        beyond = here >= reach_mm
        past[live[hit]] = np.minimum(here[hit], reach_mm)
        met[live[hit]] = True
        past[live[~hit & beyond & ~gone]] = reach_mm
        live = live[~(hit | beyond | gone)]
        k += 1
    known = np.isfinite(past)
    if not known.any():
        return None
    past, met = past[known], met[known]
    w = min(len(past), max(1, math.ceil(front_mm / h2)))
    front = float(np.sort(past)[::-1][w - 1])
    voxel = float(np.median(np.abs(tan[known]) @ sp))
    return Across(
        past_mm=front, front_mm=w * h2, rows=len(past), open_rows=int((~met).sum()), reach_mm=reach_mm, voxel_mm=voxel
    )
