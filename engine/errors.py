"""The engine's exceptions: one tree, every class defined here (httpx's documented tree).

EngineError
├── InputError              the caller's input cannot be processed (bad file, bad parameters); CLI exit code 2
│   ├── EmptySurfaceError   the iso level does not cross the data: there is no surface to build
│   ├── NoBoneInBodyError   everything at or above the bone level lies outside the body outline (a couch, a holder)
│   ├── IncompleteSeriesError  the series is not whole (missing slice, clashing duplicates, too few images)
│   ├── NotAScanError       not a scan container: neither archive nor volume file, an unreadable archive, one image
│   ├── NoSpacingError      the images do not say how large a voxel is: the caller must give the voxel size
│   ├── BudgetError         the device memory budget is too small for this scan (``needed``: one that works)
│   ├── NoSymmetryError     the bone has no mirror plane: a defect template cannot be mirrored (``engine.defect``)
│   ├── NoDefectError       mirroring finds no one-sided defect (an intact bone, or one too small to fill)
│   ├── MidlineDefectError  the defect crosses the symmetry plane: the mirror image lacks the bone too
│   └── LabelError          a label map cannot give models (``engine.io.labelmaps``, ``engine.labels``)
│       ├── NotLabelsError      the file holds no integer labels (a float NIfTI asked for as labels)
│       ├── EmptyLabelError     a label (segment) has no voxels, or the map has no label at all
│       ├── LabelsOutsideScanError  the labels do not overlap the referenced CT's grid
│       └── MissingReferenceError   a DICOM SEG whose referenced series is not there
├── PrintCheckError         the print model is not printable (not watertight, not manifold, ...): nothing written
└── StageError              a pipeline stage failed for a reason that is not the input's fault (``stage`` names it)

``InputError`` is also a ``ValueError``, so the parameter checks of ``engine.params`` (plain ``ValueError``) and the
engine's own refusals can be caught together. Callers branch on these types, never on the message text. Importing
this module never loads Warp or numpy.
"""

from __future__ import annotations

__all__ = [
    "BudgetError",
    "EmptySurfaceError",
    "EngineError",
    "IncompleteSeriesError",
    "InputError",
    "NoBoneInBodyError",
    "PrintCheckError",
    "StageError",
]


class EngineError(Exception):
    """Base class of the engine's errors."""


class InputError(EngineError, ValueError):
    """Input that the engine cannot process, with a reason a person can act on."""


class EmptySurfaceError(InputError):
    """The iso level does not cross the data: there is no surface to build."""


class NoBoneInBodyError(InputError):
    """Everything at or above the bone level lies outside the body outline (a couch, a holder): no bone model
    (``engine.volume.bodymask``)."""


class IncompleteSeriesError(InputError):
    """The series is not whole (a slice missing, two different images at one position, too few images): refused
    before anything is reconstructed, since a model built across the hole would look right and be wrong."""


class BudgetError(InputError):
    """The device memory budget (``max_device_bytes``) is too small for this scan; ``needed`` is the smallest
    budget that would work, as far as the engine can tell."""

    def __init__(self, message: str, needed: int) -> None:
        super().__init__(message)
        self.needed = int(needed)


class PrintCheckError(EngineError):
    """The print model is not printable (not watertight, not manifold, ...); the message lists every failure
    (``engine.export.printcheck``)."""


class StageError(EngineError):
    """A pipeline stage failed for a reason that is not the input's fault; ``stage`` names it (MONAI)."""

    def __init__(self, stage: str, cause: BaseException) -> None:
        super().__init__(f"stage '{stage}' failed: {type(cause).__name__}: {cause}")
        self.stage = stage


class NotAScanError(InputError):
    """The input is not a scan container bonemesh reads: neither an archive nor a volume file, a zip or tar archive
    that cannot be read, or a single 2-D image (``engine.io``; the API answers 415 Unsupported Media Type)."""


class NoSpacingError(InputError):
    """The images do not say how large a voxel is (an image stack without resolution tags, or with the pixel size but
    not the slice spacing): the caller must give the voxel size (``spacing_zyx_mm``; ``engine.io.stack``)."""


__all__ += ["NoSpacingError", "NotAScanError"]


class NoSymmetryError(InputError):
    """The bone has no mirror plane that fits it: a defect template cannot be mirrored from it (``engine.defect``)."""


class NoDefectError(InputError):
    """Mirroring the bone finds no one-sided defect: the bone is intact, or what is missing is smaller than the
    smallest defect reported (``engine.defect``)."""


class MidlineDefectError(InputError):
    """The defect crosses the symmetry plane: the mirror image lacks the same bone, so mirroring cannot make its
    template (``engine.defect``)."""


__all__ += ["MidlineDefectError", "NoDefectError", "NoSymmetryError"]


class LabelError(InputError):
    """A label map (segmentation) cannot give one model per label (``engine.io.labelmaps``, ``engine.labels``)."""


class NotLabelsError(LabelError):
    """The file holds no integer labels: a float (or scaled) NIfTI asked for as a label map, an unknown segment
    encoding."""


class EmptyLabelError(LabelError):
    """A label (a segment the file names, or one asked for) has no voxels, or the map holds no label at all."""


class LabelsOutsideScanError(LabelError):
    """The labels do not overlap the referenced CT: a segmentation of another scan or another frame of reference."""


class MissingReferenceError(LabelError):
    """A DICOM SEG whose referenced series (its CT) is not there to place its frames."""


__all__ += ["EmptyLabelError", "LabelError", "LabelsOutsideScanError", "MissingReferenceError", "NotLabelsError"]
