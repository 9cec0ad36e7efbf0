"""Segmentations in, a model per label: label maps meshed in one batch on the device (``extract``), placed as named,
coloured parts in the patient frame with their STL files (``parts``), DICOM SEG in (``dicom_seg``; the other
readers are ``engine.io.labelmaps``), and from a CT alone its largest bone pieces and a region of interest
(``pieces``). See docs/labels.md.

Public names load lazily (``engine._lazy``): importing this package loads neither Warp nor its modules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.labels.dicom_seg import read_dicom_seg, read_seg_folder
    from engine.labels.extract import LabelMesh, mesh_labels, share_by_area
    from engine.labels.parts import LabelModels, LabelPart, label_models, write_label_stls
    from engine.labels.pieces import bone_pieces, crop_roi

__all__ = [
    "LabelMesh",
    "LabelModels",
    "LabelPart",
    "bone_pieces",
    "crop_roi",
    "label_models",
    "mesh_labels",
    "read_dicom_seg",
    "read_seg_folder",
    "share_by_area",
    "write_label_stls",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "read_dicom_seg": ".dicom_seg",
        "read_seg_folder": ".dicom_seg",
        "LabelMesh": ".extract",
        "mesh_labels": ".extract",
        "share_by_area": ".extract",
        "LabelModels": ".parts",
        "LabelPart": ".parts",
        "label_models": ".parts",
        "write_label_stls": ".parts",
        "bone_pieces": ".pieces",
        "crop_roi": ".pieces",
    },
)
