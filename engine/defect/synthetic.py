"""Synthetic one-sided defects cut from an intact skull: how the template is measured (``benchmarks.defect_quality``,
``tests/engine/defect/test_defect.py``), in the manner of the AutoImplant challenges' synthetic cranial defects.

A defect is a round trephination: the skull's voxels within ``diameter_mm / 2`` of the line along ``direction``
(patient frame) through the skull's outermost point in that direction, down to ``depth_mm`` below that point; the
cut voxels take the median value of the tissue around them (samples within four voxels of the cut and more than two
voxels from any bone, past the bone's partial-volume rim), as a closed scalp over a craniectomy would leave them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.defect.grid import Grid, bone_and_skull
from engine.types import Volume


@dataclass(frozen=True)
class Cut:
    """A synthetic defect: the cut scan, the removed voxels (bool, the scan's shape) and where the cut is."""

    volume: Volume
    removed: npt.NDArray[np.bool_]
    entry_lps_mm: tuple[float, float, float]
    removed_mm3: float


def cut_defect(
    volume: Volume,
    level: float,
    direction_lps: Any,
    diameter_mm: float,
    *,
    slices: tuple[int, int] | None = None,
    depth_mm: float = 20.0,
    orient: Any = None,
    plane: Any = None,
    offset_mm: float = 0.0,
) -> Cut:
    """Cut a round defect into the skull (see the module).

    Args:
        volume: the intact scan; level: its bone level.
        direction_lps: where the defect is (patient frame; e.g. (1, -1, 1): left, anterior, superior): the cut is
            centred on the skull's outermost point in that direction and runs along it.
        diameter_mm: the trephination's diameter.
        slices: only the skull in these slices (first, last) is looked at for the outermost point (the cranium,
            not the face or the neck).
        depth_mm: how deep the cut reaches below that point.
        orient: ``OrientParams`` for an image stack.
        plane: a ``SymmetryPlane``: the outermost point is looked for on it (within a voxel), for a defect across
            the midline; ``offset_mm`` then moves the cut's centre that far toward the patient's left.
    """

    grid = Grid.of(volume, orient)
    bone, skull = bone_and_skull(volume.data, level)
    u = np.asarray(direction_lps, dtype=np.float64) @ grid.matrix  # patient direction -> grid
    u /= np.linalg.norm(u)
    idx = np.argwhere(skull)
    xyz = grid.xyz(idx)
    among = np.ones(len(idx), dtype=bool) if slices is None else (idx[:, 0] >= slices[0]) & (idx[:, 0] <= slices[1])
    if plane is not None:
        n = np.asarray(plane.normal_grid)
        among &= np.abs(xyz @ n - plane.offset_grid_mm) <= float(np.max(grid.spacing_zyx))
    if not among.any():
        raise ValueError(f"no skull in slices {slices}" + (" on the plane" if plane is not None else ""))
    k = int(np.argmax(np.where(among, xyz @ u, -np.inf)))
    top = xyz[k]
    if plane is not None:
        top = top + offset_mm * np.asarray(plane.normal_grid)
    p = xyz - top
    along = p @ u
    radial = np.linalg.norm(p - along[:, None] * u, axis=1)
    sel = (radial < diameter_mm / 2) & (along > -depth_mm)
    removed = np.zeros(volume.data.shape, dtype=bool)
    removed[tuple(idx[sel].T)] = True
    return _filled(volume, grid, bone, removed, "tissue", top)


def _filled(volume: Volume, grid: Grid, bone: Any, removed: Any, fill: str, entry: Any) -> Cut:
    """The scan with the ``removed`` bone replaced: by the median of the tissue around the cut, beyond the bone's
    partial-volume rim (2 to 4 voxels from any bone), or by the scan's air (``fill="air"``: its 1st percentile)."""
    from scipy import ndimage as ndi

    data = volume.data.copy()
    if fill == "tissue":
        around = ndi.binary_dilation(removed, iterations=4) & ~ndi.binary_dilation(bone, iterations=2)
        value = np.median(volume.data[around]) if around.any() else volume.data.min()
    else:
        value = np.percentile(volume.data, 1)
    data[removed] = np.asarray(value).astype(data.dtype)
    return Cut(
        volume=Volume(data, volume.spacing_zyx_mm, volume.origin_mm, volume.direction, volume.units,
                      dict(volume.source), volume.patient_frame),
        removed=removed,
        entry_lps_mm=tuple(float(v) for v in grid.to_patient(entry)),  # type: ignore[arg-type]
        removed_mm3=float(removed.sum()) * grid.voxel_mm3,
    )  # fmt: skip


def dice(a: npt.NDArray[np.bool_], b: npt.NDArray[np.bool_]) -> float:
    """Dice's overlap of two voxel sets."""
    total = int(a.sum()) + int(b.sum())
    return 2.0 * int((a & b).sum()) / total if total else 1.0


EDGES = ("straight", "bevelled", "ball")  # a cylinder; a cone opening 30 degrees outward; a ball on the shell
FILLS = ("tissue", "air")
BEVEL_DEG = 30.0


def _shell_depth(skull: Any, grid: Grid, entry: Any, normal: Any, reach_mm: float = 25.0) -> float:
    """How deep the shell goes under ``entry`` along ``-normal`` (grid mm): the end of the first run of skull
    samples (gaps under 3 mm, the diploe below the level, bridged)."""
    step = 0.25 * float(min(grid.spacing_zyx))
    t = np.arange(0.0, reach_mm, step)
    pts = entry[None, :] - t[:, None] * normal[None, :]
    idx = np.round(pts[:, ::-1] / np.asarray(grid.spacing_zyx)).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < np.asarray(grid.shape)), axis=1)
    inside = np.zeros(len(t), dtype=bool)
    inside[ok] = skull[tuple(idx[ok].T)]
    hit = np.flatnonzero(inside)
    if not len(hit):
        return float(max(grid.spacing_zyx))
    end = hit[0]
    for k in hit[1:]:
        if (k - end) * step > 3.0:
            break
        end = k
    return float(t[end]) + 0.5 * float(max(grid.spacing_zyx))


def _outermost(lps: Any, centre: Any, d: Any, tube_mm: float) -> int:
    """The skull voxel (index into ``lps``) farthest along the ray from ``centre`` along ``d``, within
    ``tube_mm`` of it; -1 when none."""
    rel = lps - centre
    along = rel @ d
    off = np.linalg.norm(rel - along[:, None] * d, axis=1)
    on_ray = (off <= tube_mm) & (along > 0)
    if not on_ray.any():
        return -1
    return int(np.flatnonzero(on_ray)[np.argmax(along[on_ray])])


def _outward_normal(lps: Any, centre: Any, d: Any, tube_mm: float, spread_deg: float = 12.0) -> Any:
    """The skull's outward normal (patient frame) where the ray along ``d`` leaves it: the plane through the
    outermost points of a cone of rays around it (``spread_deg``), so a thick slice's staircase does not turn it."""
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(d, up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    pts = []
    for a in np.radians(np.linspace(-spread_deg, spread_deg, 5)):
        for b in np.radians(np.linspace(-spread_deg, spread_deg, 5)):
            ray = d + np.tan(a) * e1 + np.tan(b) * e2
            k = _outermost(lps, centre, ray / np.linalg.norm(ray), tube_mm)
            if k >= 0:
                pts.append(lps[k])
    p = np.asarray(pts)
    _, axes = np.linalg.eigh(np.cov((p - p.mean(axis=0)).T))
    n = axes[:, 0]
    return n if n @ d > 0 else -n


def cut_at(
    volume: Volume,
    level: float,
    azimuth_deg: float,
    height: float,
    diameter_mm: float,
    *,
    slices: tuple[int, int],
    orient: Any = None,
    edge: str = "straight",
    fill: str = "tissue",
    depth_share: float = 1.0,
) -> Cut:
    """A full-thickness round defect anywhere on the braincase (the reviewer's sweep, issue 42).

    Args:
        azimuth_deg: the direction around the head, from anterior (0) toward the patient's left (90), posterior
            (180) and right (270), in the patient's axial plane.
        height: where between the braincase's lowest (0) and highest (1) slice of ``slices`` (patient z).
        diameter_mm: the hole's diameter (at the shell's middle).
        edge: "straight" (a cylinder along the shell's local normal), "bevelled" (a cone, ``BEVEL_DEG`` outward,
            the outer opening wider) or "ball" (a ball on the shell's middle: the opening narrows at both faces).
        fill: "tissue" (the median of the tissue around the cut, a closed scalp) or "air" (the scan's air value).
        depth_share: under 1, a partial-thickness dent: only the outer share of the shell is removed.

    The cut is centred where the ray from the braincase's axis at that height meets the skull's outer surface, runs
    along the surface's local normal (the plane through the outermost points of the rays around it) through the
    whole shell there, and removes the bone of that shape (a thin vault open at the level is cut too).
    """

    if edge not in EDGES or fill not in FILLS:
        raise ValueError(f"edge must be one of {EDGES}, fill one of {FILLS}")
    grid = Grid.of(volume, orient)
    bone, skull = bone_and_skull(volume.data, level)
    sp = np.asarray(grid.spacing_zyx)
    idx = np.argwhere(skull)
    xyz = grid.xyz(idx)
    lps = grid.to_patient(xyz)
    slab = (idx[:, 0] >= slices[0]) & (idx[:, 0] <= slices[1])
    z_lo, z_hi = np.percentile(lps[slab, 2], [2, 98])
    z = z_lo + height * (z_hi - z_lo)
    layer = slab & (np.abs(lps[:, 2] - z) <= max(2.0, float(sp.max())))
    centre = np.array([np.median(lps[layer, 0]), np.median(lps[layer, 1]), z])
    a = np.radians(azimuth_deg)
    d = np.array([np.sin(a), -np.cos(a), 0.0])
    tube = 1.5 * float(sp.max())
    k = _outermost(lps, centre, d, tube)
    if k < 0:  # a thin vault open at the level (thick slices) is not part of the skull's largest piece
        idx = np.argwhere(bone)
        xyz = grid.xyz(idx)
        lps = grid.to_patient(xyz)
        k = _outermost(lps, centre, d, tube)
    if k < 0:
        raise ValueError(f"the ray at azimuth {azimuth_deg} and height {height} meets no bone")
    entry = xyz[k]
    n_p = _outward_normal(lps, centre, d, tube)
    n = grid.from_patient(n_p) - grid.from_patient(np.zeros(3))
    depth = _shell_depth(skull, grid, entry, n)
    r = diameter_mm / 2.0
    sag = r * r / 120.0  # the curved shell's drop at the hole's edge (a 60 mm radius of curvature)
    b_idx = np.argwhere(bone)
    p = grid.xyz(b_idx) - entry
    a_n = p @ n
    radial = np.linalg.norm(p - a_n[:, None] * n, axis=1)
    mid = -0.5 * depth
    if edge == "straight":
        shape = radial < r
    elif edge == "bevelled":
        shape = radial < r + (a_n - mid) * np.tan(np.radians(BEVEL_DEG))
    else:
        shape = radial**2 + (a_n - mid) ** 2 < (r + 0.5 * depth) ** 2
    floor = depth + sag + float(sp.max()) if depth_share >= 1.0 else depth_share * depth
    sel = shape & (a_n > -floor) & (a_n < sag + float(sp.max()))
    removed = np.zeros(volume.data.shape, dtype=bool)
    removed[tuple(b_idx[sel].T)] = True
    return _filled(volume, grid, bone, removed, fill, entry)


def posed(volume: Volume, yaw_deg: float, roll_deg: float, *, orient: Any = None, mask: Any = None) -> Any:
    """The scan turned about its centre: ``yaw_deg`` about the patient's superior axis, then ``roll_deg`` about the
    anterior-posterior axis (a head turned and tilted in the scanner, the slices no longer perpendicular to the
    skull's axis), resampled (trilinear) on the same grid. With ``mask`` (bool, the scan's shape) returns the turned
    mask instead (the removed bone of a cut made before turning)."""
    from scipy import ndimage as ndi

    grid = Grid.of(volume, orient)
    y, r = np.radians(yaw_deg), np.radians(roll_deg)
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    ry = np.array([[np.cos(r), 0, np.sin(r)], [0, 1, 0], [-np.sin(r), 0, np.cos(r)]])
    rot = grid.matrix.T @ (ry @ rz) @ grid.matrix  # in the grid frame (x, y, z)
    sp = np.asarray(grid.spacing_zyx)
    c = (np.asarray(grid.shape) - 1) / 2.0
    # output index o (z, y, x) samples the input at c + S^-1 P R^T P S (o - c)
    flip = np.eye(3)[::-1]
    m = np.diag(1.0 / sp) @ flip @ rot.T @ flip @ np.diag(sp)
    offset = c - m @ c
    if mask is not None:
        out = ndi.affine_transform(mask.astype(np.float32), m, offset=offset, order=1, cval=0.0)
        return out >= 0.5
    src = volume.data.astype(np.float32)
    out = ndi.affine_transform(src, m, offset=offset, order=1, cval=float(src.min()))
    data = np.round(out).astype(volume.data.dtype) if np.issubdtype(volume.data.dtype, np.integer) else out
    return Volume(data, volume.spacing_zyx_mm, volume.origin_mm, volume.direction, volume.units, dict(volume.source),
                  volume.patient_frame)  # fmt: skip
