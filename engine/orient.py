"""Where a model lies: from the grid to the patient (the STL), and from the patient to glTF (the viewers).

Frames, all right-handed:

* **grid**: the engine's meshes (``engine.types.Mesh``): vertices in mm from the first sample along the array
  axes, stored in (z, y, x) order.
* **patient**: DICOM's patient frame, LPS, in mm: +x toward the patient's left, +y posterior, +z superior.
  ``model.stl`` is written in it. A DICOM series places its grid there with ImagePositionPatient (the origin) and
  ImageOrientationPatient (the axes): ``p = origin + direction @ (x, y, z)``. An image stack carries no
  orientation and follows ``OrientParams``: by default the DICOM axial display (column index toward the
  patient's left, row index posterior) with the first slice superior; its box keeps its place, from 0 to its
  extent on every axis (a reversed axis counts from the far end).
* **glTF**: metres, +Y superior, +Z anterior (the patient faces +Z, toward the default camera), +X the patient's
  left, centred on the model's bounding box: ``g = 0.001 * R @ (p - centre)`` with ``R`` the rotation of
  ``engine.export.glb`` (x, y, z) -> (x, z, -y). ``model.glb``, ``phone.glb`` and ``ar.glb`` share the centre,
  which the report keeps (``frame.gltf_centre_lps_mm``), so a glTF position maps back to the STL.

A mirroring map (a stack flipped an odd number of times) reverses the faces' winding so that they stay outward.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from engine.params import OrientParams
from engine.types import Mesh, Volume

if TYPE_CHECKING:
    from engine.report import FrameInfo

PATIENT_FRAME = "LPS mm (DICOM patient frame: +x patient's left, +y posterior, +z superior)"
GLTF_FRAME = "metres, +Y superior, +Z anterior (the patient faces +Z), +X patient's left, centred on the bounding box"


@dataclass(frozen=True)
class Frame:
    """An affine map from grid (x, y, z) mm to patient LPS mm: ``p = matrix @ g + offset_mm``.

    Args:
        matrix: 3x3, orthonormal (columns: the grid's x, y, z axes in the patient frame).
        offset_mm: (3,) the patient position of the first sample.
        placed_by: how the placement is known (DICOM headers, or the stack convention in words).
    """

    matrix: npt.NDArray[np.float64]
    offset_mm: npt.NDArray[np.float64]
    placed_by: str

    @property
    def mirrored(self) -> bool:
        """Whether the map reverses handedness (the faces' winding must be reversed)."""
        return bool(np.linalg.det(self.matrix) < 0)

    def to_dict(self) -> FrameInfo:
        """The report's ``frame`` entry (JSON-able): the map as a 4x4 matrix on grid (x, y, z, 1) in mm."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.matrix, self.offset_mm
        return {
            "stl": PATIENT_FRAME,
            "gltf": GLTF_FRAME,
            "placed_by": self.placed_by,
            "patient_from_grid_xyz": [[round(float(v), 9) for v in row] for row in m],
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> Frame:
        """Inverse of :meth:`to_dict`; None gives the identity (grid = patient)."""
        if not data:
            return cls(np.eye(3), np.zeros(3), "identity (no frame recorded)")
        m = np.asarray(data["patient_from_grid_xyz"], dtype=np.float64)
        return cls(m[:3, :3], m[:3, 3], str(data.get("placed_by", "")))


def describe_stack_convention(orient: OrientParams) -> str:
    """The stack convention in words (for the report and the CLI's summary)."""
    return (
        f"image stack convention: first slice {orient.first_slice}, "
        f"image left = patient's {'left' if orient.flip_lr else 'right'}, "
        f"image top = {'posterior' if orient.flip_ap else 'anterior'}"
    )


def patient_frame(volume: Volume, orient: OrientParams | None = None) -> Frame:
    """The grid -> patient map of a volume: from its DICOM geometry, or from ``orient`` for an image stack.

    Args:
        volume: the scan; ``volume.patient_frame`` says whether ``origin_mm``/``direction`` are in LPS (placed by
            ``source["placed_by"]`` where the reader says how, e.g. a NIfTI label map's sform; else DICOM's headers).
        orient: the stack's orientation (default ``OrientParams()``); ignored for DICOM.

    Returns:
        The map (see :class:`Frame`).
    """
    if volume.patient_frame:
        matrix = np.asarray(volume.direction, dtype=np.float64)
        # what placed it: a DICOM series' headers, or a label map's own words (its NIfTI sform, NRRD space, SEG)
        placed = str(volume.source.get("placed_by") or "DICOM ImagePositionPatient/Orientation")
        return Frame(matrix, np.asarray(volume.origin_mm, dtype=np.float64), placed)
    o = orient or OrientParams()
    superior_first = o.first_slice == "superior"
    signs = np.array([-1.0 if o.flip_lr else 1.0, -1.0 if o.flip_ap else 1.0, -1.0 if superior_first else 1.0])
    # the stack's box stays where it was, from 0 to its extent on every axis: a reversed axis starts at the far end
    extent_xyz = np.array([(n - 1) * s for n, s in zip(volume.data.shape, volume.spacing_zyx_mm, strict=True)])[::-1]
    offset = np.where(signs < 0, extent_xyz, 0.0) + signs * np.asarray(volume.origin_mm, dtype=np.float64)
    return Frame(np.diag(signs), offset, describe_stack_convention(o))


def to_patient(mesh: Mesh, frame: Frame) -> Mesh:
    """The mesh in the patient frame, in the ``Mesh`` layout: ``vertices[:, ::-1]`` are LPS (x, y, z) in mm.

    Normals are rotated with the vertices; faces are reversed when the map mirrors, so they stay outward.
    """
    xyz = mesh.vertices[:, ::-1].astype(np.float64) @ frame.matrix.T + frame.offset_mm
    faces = mesh.faces[:, ::-1].copy() if frame.mirrored else mesh.faces
    normals = None
    if mesh.normals is not None:
        normals = (mesh.normals[:, ::-1].astype(np.float64) @ frame.matrix.T)[:, ::-1].astype(np.float32)
    return Mesh(np.ascontiguousarray(xyz[:, ::-1], dtype=np.float32), np.ascontiguousarray(faces), normals)


def centred(mesh: Mesh) -> tuple[Mesh, npt.NDArray[np.float64]]:
    """The mesh moved so that its bounding box is centred on the origin, and the centre (x, y, z) it had."""
    v = mesh.vertices.astype(np.float64)
    centre_zyx = (v.min(axis=0) + v.max(axis=0)) / 2 if len(v) else np.zeros(3)
    moved = (v - centre_zyx).astype(np.float32)
    return Mesh(moved, mesh.faces, mesh.normals), centre_zyx[::-1]


def export_meshes(mesh: Mesh, frame: FrameInfo | None) -> tuple[Mesh, Mesh, FrameInfo]:
    """The print mesh (patient LPS mm) and the viewing mesh (patient axes, centred: the glTF files), and the report's
    ``frame`` entry with the centre added.

    Args:
        mesh: the pipeline's mesh in grid coordinates.
        frame: the report's ``frame`` entry (:meth:`Frame.to_dict`); None: grid = patient.
    """
    f = Frame.from_dict(frame)
    patient = to_patient(mesh, f)
    viewing, centre = centred(patient)
    info: FrameInfo = {**(frame or f.to_dict()), "gltf_centre_lps_mm": [round(float(c), 6) for c in centre]}
    return patient, viewing, info
