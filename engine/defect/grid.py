"""Where the defect's voxels lie: the grid's millimetres, the patient frame, planes and mirror images, the skull.

Coordinates: ``grid`` is (x, y, z) in mm from the first sample along the array axes (``index * spacing``, index in
(z, y, x) order reversed); ``patient`` is LPS mm through ``engine.orient``'s frame (DICOM headers, or the stack
convention of ``OrientParams``). The map is rigid (an orthonormal matrix and an offset), so a mirror plane found in
the grid is the same plane in the patient frame (:meth:`Grid.plane_to_patient`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.types import Volume

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
# the skull: the largest 26-connected piece at or above the level (couch and head holders are separate pieces)
CONNECTIVITY = np.ones((3, 3, 3), dtype=bool)


@dataclass(frozen=True)
class Grid:
    """The volume's sampling and placement.

    Args:
        shape: (z, y, x) samples.
        spacing_zyx: voxel size (z, y, x) in mm.
        matrix: grid (x, y, z) -> patient rotation (orthonormal 3x3, ``engine.orient.Frame.matrix``).
        offset_mm: patient position of the first sample.
        placed_by: how the placement is known (the frame's words).
    """

    shape: tuple[int, int, int]
    spacing_zyx: tuple[float, float, float]
    matrix: FloatArray
    offset_mm: FloatArray
    placed_by: str

    @classmethod
    def of(cls, volume: Volume, orient: Any = None) -> Grid:
        """The grid of a volume; ``orient`` (``engine.params.OrientParams``) places an image stack."""
        from engine.orient import patient_frame

        frame = patient_frame(volume, orient)
        shape = tuple(int(n) for n in volume.data.shape)
        spacing = tuple(float(s) for s in volume.spacing_zyx_mm)
        return cls(shape, spacing, frame.matrix, frame.offset_mm, frame.placed_by)  # type: ignore[arg-type]

    @property
    def spacing_xyz(self) -> FloatArray:
        return np.asarray(self.spacing_zyx[::-1], dtype=np.float64)

    @property
    def voxel_mm3(self) -> float:
        return float(np.prod(self.spacing_zyx))

    def xyz(self, index_zyx: npt.ArrayLike) -> FloatArray:
        """Grid mm (x, y, z) of (N, 3) indices (z, y, x)."""
        return np.asarray(index_zyx, dtype=np.float64)[..., ::-1] * self.spacing_xyz

    def to_patient(self, xyz: npt.ArrayLike) -> FloatArray:
        return np.asarray(xyz, dtype=np.float64) @ self.matrix.T + self.offset_mm

    def from_patient(self, lps: npt.ArrayLike) -> FloatArray:
        return (np.asarray(lps, dtype=np.float64) - self.offset_mm) @ self.matrix

    def direction_to_patient(self, v: npt.ArrayLike) -> FloatArray:
        return np.asarray(v, dtype=np.float64) @ self.matrix.T

    def plane_to_patient(self, normal: FloatArray, offset: float) -> tuple[FloatArray, float]:
        """The plane ``normal . g = offset`` (grid) as ``n . p = offset'`` (patient)."""
        n = self.direction_to_patient(normal)
        return n, float(offset + n @ self.offset_mm)

    def plane_from_patient(self, normal: FloatArray, offset: float) -> tuple[FloatArray, float]:
        n = np.asarray(normal, dtype=np.float64) @ self.matrix
        return n, float(offset - np.asarray(normal, dtype=np.float64) @ self.offset_mm)

    def left_in_grid(self) -> FloatArray:
        """The patient's left (+x of LPS) as a grid direction."""
        return np.asarray(self.matrix[0], dtype=np.float64)  # row 0 of M = M^T e_x


def reflect(points: FloatArray, normal: FloatArray, offset: float) -> FloatArray:
    """Mirror images of (N, 3) points across the plane ``normal . p = offset`` (unit normal)."""
    s = points @ normal - offset
    return points - 2.0 * s[..., None] * normal


def bone_at(data: npt.NDArray[Any], level: float) -> BoolArray:
    """Every sample at or above the level.

    Raises:
        EmptySurfaceError: nothing is at or above the level.
    """
    from engine.errors import EmptySurfaceError

    bone = np.asarray(data >= level)
    if not bone.any():
        lo, hi = float(np.min(data)), float(np.max(data))
        raise EmptySurfaceError(f"no bone at level {level:g}: the scan's values run from {lo:g} to {hi:g}")
    return bone


def bone_and_skull(data: npt.NDArray[Any], level: float) -> tuple[BoolArray, BoolArray]:
    """The bone (every sample at or above the level) and the skull: its largest 26-connected piece, which leaves out
    a couch, a head holder and loose specks.

    Raises:
        EmptySurfaceError: nothing is at or above the level.
    """
    from scipy import ndimage as ndi

    bone = bone_at(data, level)
    labels, n = ndi.label(bone, structure=CONNECTIVITY)
    if n == 1:
        return bone, bone.copy()
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return bone, labels == int(sizes.argmax())


def bounding_box(mask: BoolArray) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(lo, hi) indices (z, y, x) of the set voxels, hi exclusive."""
    lo, hi = [], []
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        hit = np.flatnonzero(mask.any(axis=other))
        lo.append(int(hit[0]))
        hi.append(int(hit[-1]) + 1)
    return np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)


def surface_voxels(mask: BoolArray) -> npt.NDArray[np.int64]:
    """(N, 3) indices (z, y, x) of the mask's voxels with a face neighbour outside it (array borders count as
    outside)."""
    from scipy import ndimage as ndi

    lo, hi = bounding_box(mask)
    sub = mask[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    inner = ndi.binary_erosion(np.pad(sub, 1), border_value=0)[1:-1, 1:-1, 1:-1]
    return np.argwhere(sub & ~inner) + lo


DENSE_SHARE = 32  # ``label_voxels`` labels the voxels' box with scipy where they fill more than 1/32 of it
# the 13 neighbour steps (z, y, x) of the 26 that come later in raster order: each pair of touching voxels once
_LATER = np.array([(dz, dy, dx) for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                   if (dz, dy, dx) > (0, 0, 0)], dtype=np.int64)  # fmt: skip


def label_voxels(flat: npt.NDArray[np.int64], shape: tuple[int, ...]) -> tuple[npt.NDArray[np.int64], int]:
    """The 26-connected pieces of a few voxels of a large volume: ``flat``, their ascending flat indices in a C-order
    volume of ``shape`` (z, y, x). Per voxel its piece (1 .. n) and n, numbered as ``scipy.ndimage.label`` numbers
    them (by each piece's first voxel in raster order), from a graph of the voxels' touching pairs: no pass over the
    whole volume (the rules' grown voxels are thousands scattered over a crop of millions)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(flat)
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0
    dims = tuple(int(s) for s in shape)
    coords = np.unravel_index(flat, dims)
    lo = np.array([int(c.min()) for c in coords])
    hi = np.array([int(c.max()) + 1 for c in coords])
    if n * DENSE_SHARE >= int(np.prod(hi - lo)):  # dense within their box: scipy's pass over the box is faster
        from scipy import ndimage as ndi

        box = np.zeros(tuple(int(v) for v in hi - lo), dtype=bool)
        local = tuple(c - a for c, a in zip(coords, lo, strict=True))
        box[local] = True
        labels, count = ndi.label(box, structure=CONNECTIVITY)
        return labels[local].astype(np.int64), int(count)
    # per axis, whether a step back (-1) or on (+1) stays inside the array
    fits = [{-1: c > 0, 1: c < d - 1} for c, d in zip(coords, dims, strict=True)]
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    rows, cols = [], []
    for step in _LATER:
        ok = np.ones(n, dtype=bool)
        for axis, v in enumerate(step):
            if v:
                ok &= fits[axis][int(v)]
        inside = np.flatnonzero(ok)
        want = flat[inside] + int(step @ strides)
        at = np.minimum(np.searchsorted(flat, want), n - 1)
        hit = flat[at] == want
        rows.append(inside[hit])
        cols.append(at[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n, n))
    count, piece = connected_components(graph, directed=False)
    _, first = np.unique(piece, return_index=True)  # each piece's first voxel (the voxels are in raster order)
    rank = np.empty(count, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(1, count + 1)
    return rank[piece], int(count)


def touching(mask: BoolArray) -> BoolArray:
    """The mask's voxels and every voxel touching one of them (26-connected): ``scipy.ndimage.binary_dilation`` with
    the 3 x 3 x 3 cube (``CONNECTIVITY``). The cube is separable: a voxel's step along each axis in turn gives it,
    six shifted ors instead of 26 per voxel."""
    out = np.array(mask, dtype=bool, copy=True)
    for axis in range(out.ndim):
        src = out.copy()
        lo = [slice(None)] * out.ndim
        hi = [slice(None)] * out.ndim
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        out[tuple(hi)] |= src[tuple(lo)]
        out[tuple(lo)] |= src[tuple(hi)]
    return out
