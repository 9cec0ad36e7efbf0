"""The implant: the surface of the defect template, watertight, in the patient frame (mm).

The surface is Marching Cubes 33 (``engine.isosurface``, closed) at 0 of a field on the template's box:

* inside the template: ``min(mirrored - level, level - sample)``, >= 0 (mirrored bone, no bone in the scan);
* on bone of the scan: ``level - sample`` (< 0), so the implant's rim lies on the bone's own iso-surface and fits it;
* elsewhere: ``mirrored - level`` where the mirror has no bone (the implant's faces follow the mirrored shell's),
  else ``-contrast / 2`` (where the template was cut from a sliver beside it: halfway).

Pieces of the surface under ``SPECK_VOXELS`` voxels are dropped (``engine.surface.remove_islands``). The vertices go
from the grid to the patient frame as ``model.stl``'s do (``engine.orient``); a large surface is decimated lightly
(``engine.decimation``: quadric edge collapse that keeps the topology) to ``max_faces``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from engine.defect.grid import Grid, bounding_box
from engine.types import Mesh

MARGIN = 2  # voxels of field around the template
SPECK_VOXELS = 8.0  # pieces of the surface smaller than this many voxels are dropped


def implant_field(
    mask: npt.NDArray[np.bool_],
    data: npt.NDArray[np.float32],
    mirrored: npt.NDArray[np.float32],
    level: float,
    contrast: float,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """The field (see the module) on the template's box widened by ``MARGIN``, and the box's first voxel."""
    lo, hi = bounding_box(mask)
    lo = np.maximum(lo - MARGIN, 0)
    hi = np.minimum(hi + MARGIN, mask.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    inside, d, m = mask[box], data[box], mirrored[box]
    outside = np.where(d >= level, level - d, np.where(m < level, m - level, -0.5 * contrast))
    field = np.where(inside, np.minimum(m - level, level - d), outside)
    return np.ascontiguousarray(field, dtype=np.float32), lo


def implant_mesh(
    mask: npt.NDArray[np.bool_],
    lo: npt.NDArray[np.int64],
    data: npt.NDArray[np.float32],
    mirrored: npt.NDArray[np.float32],
    level: float,
    contrast: float,
    grid: Grid,
    *,
    device: Any = "auto",
    max_faces: int | None = None,
) -> tuple[Mesh, dict[str, Any]]:
    """The implant's surface in the patient frame (``Mesh`` layout: ``vertices[:, ::-1]`` are LPS mm) and what was
    done (faces before and after decimation).

    Args:
        mask: the template's voxels on a crop whose first voxel is ``lo`` in the whole grid.
        data, mirrored: the scan and its mirror image on the same crop (float32).
        level: the bone level; contrast: level minus the tissue around the bone.
        grid: the volume's sampling and placement.
    """
    from engine.isosurface import marching_cubes_33
    from engine.orient import Frame, to_patient

    field, box_lo = implant_field(mask, data, mirrored, level, contrast)
    sp = grid.spacing_zyx
    verts, faces = marching_cubes_33(field, 0.0, spacing=sp, device=device, closed=True)
    verts = (verts.astype(np.float64) + (box_lo + lo) * np.asarray(sp)).astype(np.float32)
    info: dict[str, Any] = {"mc33_faces": len(faces), "decimated": False}
    if len(faces):  # specks of the surface (a voxel's worth where the template thins out) are not printed
        from engine.surface import remove_islands

        verts, faces, isl = remove_islands(verts, faces, min_volume_mm3=SPECK_VOXELS * grid.voxel_mm3)
        info["specks_removed"] = int(isl["removed_pieces"])
    if max_faces is not None and len(faces) > max_faces:
        from engine.decimation import decimate_mesh

        verts, faces, dec = decimate_mesh(verts, faces, max_triangles=max_faces, device=device)
        info.update(decimated=True, decimation={k: dec[k] for k in ("output_faces", "closed_output", "volume_change")})
    frame = Frame(grid.matrix, grid.offset_mm, grid.placed_by)
    return to_patient(Mesh(verts, faces), frame), info
