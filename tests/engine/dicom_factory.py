"""Synthetic DICOM CT series for tests, written with pydicom (no real patient data)."""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.filewriter import dcmwrite
from pydicom.uid import (
    CTImageStorage,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    MediaStorageDirectoryStorage,
    generate_uid,
)

# identifiers that must never reach Volume.source
PATIENT = {"PatientName": "DOE^JANE", "PatientID": "PID-0042", "PatientBirthDate": "19700101"}
STUDY_UID = "1.2.826.0.1.3680043.8.498.1"
FRAME_OF_REFERENCE_UID = "1.2.826.0.1.3680043.8.498.2"


def ct_slice(
    pixels: np.ndarray,
    *,
    ipp: Sequence[float],
    iop: Sequence[float] = (1, 0, 0, 0, 1, 0),
    pixel_spacing: tuple[float, float] = (0.5, 0.5),
    series_uid: str,
    instance: int,
    slope: float = 1.0,
    intercept: float = -1024.0,
    modality: str = "CT",
    transfer_syntax: str = ExplicitVRLittleEndian,
    preamble: bool = True,
    description: str = "SYNTHETIC",
    tilt_deg: float | None = None,
    study_uid: str = STUDY_UID,
    image_type: Sequence[str] = ("ORIGINAL", "PRIMARY", "AXIAL"),
) -> bytes:
    """One single-frame image as file bytes. ``pixels`` are the stored values (uint16 or int16)."""
    ds = Dataset()
    for key, value in PATIENT.items():
        setattr(ds, key, value)
    ds.SOPClassUID = CTImageStorage
    ds.SOPInstanceUID = generate_uid()
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.FrameOfReferenceUID = FRAME_OF_REFERENCE_UID
    ds.ImageType = list(image_type)
    ds.Modality = modality
    ds.Manufacturer = "BONEMESH TEST"
    ds.SeriesDescription = description
    ds.InstanceNumber = instance
    ds.ImagePositionPatient = [f"{v:.6f}" for v in ipp]
    ds.ImageOrientationPatient = [f"{v:.7f}" for v in iop]
    ds.PixelSpacing = [f"{v:g}" for v in pixel_spacing]
    ds.SliceThickness = "1"
    ds.RescaleSlope = f"{slope:g}"
    ds.RescaleIntercept = f"{intercept:g}"
    if tilt_deg is not None:
        ds.GantryDetectorTilt = f"{tilt_deg:g}"
    signed = pixels.dtype == np.int16
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = pixels.shape
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = int(signed)
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<i2" if signed else "<u2").tobytes()
    buf = io.BytesIO()
    if not preamble:  # a bare Implicit VR data set: no preamble, no "DICM", no group 0002
        dcmwrite(buf, ds, implicit_vr=True, little_endian=True, enforce_file_format=False)
        return buf.getvalue()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    if transfer_syntax not in (ExplicitVRLittleEndian, ImplicitVRLittleEndian):
        ds.compress(transfer_syntax)
    elif transfer_syntax == ImplicitVRLittleEndian:
        ds.file_meta.TransferSyntaxUID = ImplicitVRLittleEndian
    dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()


def dicomdir_like() -> bytes:
    """A DICOM file with no pixel data (like a DICOMDIR or Philips DIRFILE)."""
    ds = Dataset()
    ds.FileSetID = "TEST"
    ds.PatientName = PATIENT["PatientName"]
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = MediaStorageDirectoryStorage
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    buf = io.BytesIO()
    dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()


def series(
    field: Callable[[np.ndarray], np.ndarray],
    *,
    positions_mm: Sequence[float],
    shape: tuple[int, int] = (24, 20),
    pixel_spacing: tuple[float, float] = (0.5, 0.5),
    iop: Sequence[float] = (1, 0, 0, 0, 1, 0),
    drift: Sequence[float] = (0.0, 0.0, 0.0),
    origin: Sequence[float] = (-5.0, -6.0, 0.0),
    series_uid: str | None = None,
    name: str = "IM",
    **kwargs: object,
) -> dict[str, bytes]:
    """Files of a series sampling ``field`` (HU at patient points (..., 3) in mm; stored as HU + 1024).

    Slice k lies at ``origin + positions_mm[k] * normal + positions_mm[k] * drift`` (``drift`` in-plane gives the
    shear of a gantry tilt). Names are ``{name}{k + 1}`` (no extension), in slice order.
    """
    iop_a = np.asarray(iop, dtype=float)
    row, col = iop_a[:3], iop_a[3:]
    normal = np.cross(row, col)
    uid = series_uid or generate_uid()
    jj, ii = np.mgrid[0 : shape[0], 0 : shape[1]]
    files: dict[str, bytes] = {}
    for k, d in enumerate(positions_mm):
        ipp = np.asarray(origin, dtype=float) + d * normal + d * np.asarray(drift, dtype=float)
        pts = ipp + ii[..., None] * pixel_spacing[1] * row + jj[..., None] * pixel_spacing[0] * col
        stored = np.rint(field(pts) + 1024).astype(np.uint16)
        files[f"{name}{k + 1}"] = ct_slice(
            stored, ipp=ipp, iop=iop, pixel_spacing=pixel_spacing, series_uid=uid, instance=k + 1, **kwargs
        )
    return files


def break_rle(files: dict[str, bytes], names: Sequence[str]) -> None:
    """Make the RLE pixel data of ``names`` undecodable, in place: each first frame's header claims 9 segments."""
    for name in names:
        data = bytearray(files[name])
        frame = data.find(b"\xfe\xff\x00\xe0", data.find(b"\xfe\xff\x00\xe0") + 8) + 8  # after the offset table
        data[frame : frame + 4] = (9).to_bytes(4, "little")
        files[name] = bytes(data)
