"""Data types shared by the engine's stages (numpy only: importing this never loads Warp)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt


@dataclass
class Volume:
    """A scan on a regular grid.

    Args:
        data: (z, y, x) samples (uint8, uint16, int16 or float32).
        spacing_zyx_mm: voxel size along z, y, x in mm (all > 0).
        origin_mm: position of sample (0, 0, 0) in patient/scanner coordinates (x, y, z) in mm.
        direction: 3x3 matrix whose columns are the unit vectors of the x, y, z array axes in patient
            coordinates (identity for image stacks).
        units: "HU" for CT in Hounsfield units, "raw" otherwise.
        source: metadata about where the data came from (format, file count, series description...), never
            patient identifiers.
        patient_frame: True when ``origin_mm`` and ``direction`` place the grid in DICOM's patient frame (LPS:
            +x the patient's left, +y posterior, +z superior), i.e. for DICOM with ImagePositionPatient and
            ImageOrientationPatient; False for image stacks, whose orientation comes from
            ``engine.params.OrientParams`` (see ``engine.orient``).
        instances: for DICOM, the images the volume was built from, in slice order: (SOP Class UID, SOP Instance
            UID, frame number or None); what an Encapsulated STL references. Not in the report.
    """

    data: npt.NDArray[Any]
    spacing_zyx_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    units: str = "raw"
    source: dict[str, Any] = field(default_factory=dict)
    patient_frame: bool = False
    instances: tuple[tuple[str, str, int | None], ...] = ()


@dataclass
class Mesh:
    """A triangle mesh: vertices (V, 3) float32 in (z, y, x) order, mm; faces (F, 3) int32, outward normals with
    vertices taken in (x, y, z) order; optional per-vertex unit normals (V, 3) float32 in (z, y, x) order."""

    vertices: npt.NDArray[np.float32]
    faces: npt.NDArray[np.int32]
    normals: npt.NDArray[np.float32] | None = None
