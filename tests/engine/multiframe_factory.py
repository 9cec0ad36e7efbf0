"""Multi-frame Enhanced CT images for tests, assembled with pydicom from single-frame images (no real patient data
unless the source holds some: the real scans in ../shared/data are phantoms).

The frames keep the source images' stored pixels (or re-stored under another rescale), positions, orientation and
pixel spacing, so a multi-frame file and the single-frame series it came from must load as the same volume.
"""

from __future__ import annotations

import io
from collections.abc import Collection, Sequence

import numpy as np
from pydicom import dcmread
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.filewriter import dcmwrite
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import (
    EnhancedCTImageStorage,
    ExplicitVRLittleEndian,
    LegacyConvertedEnhancedCTImageStorage,
    generate_uid,
)

# the macros the Shared Functional Groups Sequence holds by default (Plane Position is always per frame)
SHARED = ("PixelMeasuresSequence", "PlaneOrientationSequence", "PixelValueTransformationSequence")
MACROS = (*SHARED, "PlanePositionSequence")
_COPIED = (
    "SpecificCharacterSet",
    "PatientName",
    "PatientID",
    "PatientBirthDate",
    "StudyInstanceUID",
    "SeriesInstanceUID",
    "SeriesNumber",
    "SeriesDescription",
    "FrameOfReferenceUID",
    "Modality",
    "Manufacturer",
)
_FRAME_TYPE = ["ORIGINAL", "PRIMARY", "AXIAL", "NONE"]


def _item(**values: object) -> Dataset:
    ds = Dataset()
    for key, value in values.items():
        setattr(ds, key, value)
    return ds


def _macro(src: Dataset, keyword: str, rescale: tuple[float, float]) -> DicomSequence:
    """One functional group macro of a source image, as a sequence of one item."""
    if keyword == "PlanePositionSequence":
        item = _item(ImagePositionPatient=list(src.ImagePositionPatient))
    elif keyword == "PlaneOrientationSequence":
        item = _item(ImageOrientationPatient=list(src.ImageOrientationPatient))
    elif keyword == "PixelMeasuresSequence":
        item = _item(PixelSpacing=list(src.PixelSpacing), SliceThickness=src.get("SliceThickness", "1"))
    elif keyword == "PixelValueTransformationSequence":
        item = _item(RescaleSlope=f"{rescale[0]:g}", RescaleIntercept=f"{rescale[1]:g}", RescaleType="HU")
    else:
        raise ValueError(f"no such macro here: {keyword}")
    return DicomSequence([item])


def _restored(src: Dataset, rescale: tuple[float, float]) -> np.ndarray:
    """The source's pixels stored under ``rescale`` (slope, intercept): the same rescaled values, exactly."""
    pixels = src.pixel_array
    slope0, inter0 = float(src.get("RescaleSlope", 1)), float(src.get("RescaleIntercept", 0))
    if rescale == (slope0, inter0):
        return pixels
    values = (pixels.astype(np.float64) * slope0 + inter0 - rescale[1]) / rescale[0]
    stored = np.rint(values)
    info = np.iinfo(pixels.dtype)
    if not np.array_equal(stored, values) or stored.min() < info.min or stored.max() > info.max:
        raise ValueError(f"rescale {rescale} cannot store the values of the source exactly in {pixels.dtype}")
    return stored.astype(pixels.dtype)


def enhanced_ct(
    slices: Sequence[bytes | Dataset],
    *,
    order: Sequence[int] | None = None,
    shared: Collection[str] = SHARED,
    rescale: Sequence[tuple[float, float]] | None = None,
    without_position: Collection[int] = (),
    legacy: bool = False,
    series_uid: str | None = None,
    transfer_syntax: str = ExplicitVRLittleEndian,
) -> bytes:
    """One multi-frame (Enhanced or Legacy Converted Enhanced) CT file holding ``slices`` as its frames.

    Args:
        slices: single-frame CT images (file bytes or data sets), e.g. ``dicom_factory.series`` or a real scan.
        order: frame i is ``slices[order[i]]`` (default: the slices in the order given). The Frame Content's
            In-Stack Position Number and Dimension Index Values give each frame's rank in ``slices``.
        shared: the macros (of ``SHARED``) held once in the Shared Functional Groups; the others are per frame.
        rescale: (slope, intercept) of each slice (indexed like ``slices``): its pixels are stored under it
            (default: the slice's own rescale).
        without_position: frames (file order) left without a Plane Position (Patient).
        legacy: a Legacy Converted Enhanced CT Image instead of an Enhanced CT Image.
        series_uid: default the first slice's SeriesInstanceUID (files made from parts of one series stay one).
        transfer_syntax: e.g. RLE Lossless or JPEG 2000 Lossless (encoded frame by frame by pydicom).
    """
    sources = [s if isinstance(s, Dataset) else dcmread(io.BytesIO(s)) for s in slices]
    order = list(range(len(sources))) if order is None else list(order)
    own = [(float(s.get("RescaleSlope", 1)), float(s.get("RescaleIntercept", 0))) for s in sources]
    rescales = own if rescale is None else [(float(a), float(b)) for a, b in rescale]
    if "PixelValueTransformationSequence" in shared and len(set(rescales)) > 1:
        raise ValueError("frames of different rescales cannot share one Pixel Value Transformation")
    ref = sources[order[0]]
    ds = Dataset()
    for keyword in _COPIED:
        if keyword in ref:
            setattr(ds, keyword, ref.data_element(keyword).value)  # type: ignore[union-attr]
    if series_uid is not None:
        ds.SeriesInstanceUID = series_uid
    ds.SOPClassUID = LegacyConvertedEnhancedCTImageStorage if legacy else EnhancedCTImageStorage
    ds.SOPInstanceUID = generate_uid()
    ds.ImageType = list(_FRAME_TYPE)
    ds.InstanceNumber = 1
    ds.ContentQualification = "RESEARCH"
    for keyword in ("SamplesPerPixel", "PhotometricInterpretation", "Rows", "Columns"):
        setattr(ds, keyword, ref.data_element(keyword).value)  # type: ignore[union-attr]
    for keyword in ("BitsAllocated", "BitsStored", "HighBit", "PixelRepresentation"):
        setattr(ds, keyword, ref.data_element(keyword).value)  # type: ignore[union-attr]
    ds.NumberOfFrames = len(order)
    ds.DimensionOrganizationSequence = DicomSequence([_item(DimensionOrganizationUID=generate_uid())])
    organization = ds.DimensionOrganizationSequence[0].DimensionOrganizationUID
    ds.DimensionIndexSequence = DicomSequence(
        [
            _item(
                DimensionOrganizationUID=organization,
                DimensionIndexPointer=pointer,
                FunctionalGroupPointer=0x00209111,  # Frame Content Sequence
            )
            for pointer in (0x00209056, 0x00209057)  # Stack ID, In-Stack Position Number
        ]
    )
    first = order[0]
    shared_item = _item(CTImageFrameTypeSequence=DicomSequence([_item(FrameType=list(_FRAME_TYPE))]))
    for keyword in shared:
        setattr(shared_item, keyword, _macro(sources[first], keyword, rescales[first]))
    ds.SharedFunctionalGroupsSequence = DicomSequence([shared_item])
    per_frame = []
    for i, k in enumerate(order):
        rank = k + 1
        item = _item(
            FrameContentSequence=DicomSequence(
                [_item(StackID="1", InStackPositionNumber=rank, DimensionIndexValues=[1, rank])]
            )
        )
        for keyword in MACROS:
            if keyword in shared or (keyword == "PlanePositionSequence" and i in without_position):
                continue
            setattr(item, keyword, _macro(sources[k], keyword, rescales[k]))
        per_frame.append(item)
    ds.PerFrameFunctionalGroupsSequence = DicomSequence(per_frame)
    frames = np.stack([_restored(sources[k], rescales[k]) for k in order])
    ds.PixelData = np.ascontiguousarray(frames, dtype=frames.dtype.newbyteorder("<")).tobytes()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    if transfer_syntax != ExplicitVRLittleEndian:
        ds.compress(transfer_syntax)
    buf = io.BytesIO()
    dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()
