"""Synthetic one-sided defects cut from an intact skull: how the template is measured (``benchmarks.defect_quality``,
``tests/engine/test_defect.py``), in the manner of the AutoImplant challenges' synthetic cranial defects.

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
    from scipy import ndimage as ndi

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
    # the tissue around the cut, beyond the bone's partial-volume rim (2 to 4 voxels from any bone)
    around = ndi.binary_dilation(removed, iterations=4) & ~ndi.binary_dilation(bone, iterations=2)
    fill = np.median(volume.data[around]) if around.any() else volume.data.min()
    data = volume.data.copy()
    data[removed] = np.asarray(fill).astype(data.dtype)
    return Cut(
        volume=Volume(data, volume.spacing_zyx_mm, volume.origin_mm, volume.direction, volume.units,
                      dict(volume.source), volume.patient_frame),
        removed=removed,
        entry_lps_mm=tuple(float(v) for v in grid.to_patient(top)),  # type: ignore[arg-type]
        removed_mm3=float(removed.sum()) * grid.voxel_mm3,
    )  # fmt: skip


def dice(a: npt.NDArray[np.bool_], b: npt.NDArray[np.bool_]) -> float:
    """Dice's overlap of two voxel sets."""
    total = int(a.sum()) + int(b.sum())
    return 2.0 * int((a & b).sum()) / total if total else 1.0
