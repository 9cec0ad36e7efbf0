"""Encapsulated STL (DICOM PS3.3 A.85, SOP Class 1.2.840.10008.5.1.4.1.1.104.3, modality M3D): a print model that
goes back into the hospital's archive beside the CT it was built from.

``to_encapsulated_stl`` is a pure function, mesh + the source CT's attributes -> the DICOM file's bytes:

* the mesh must already lie in the source's patient frame (LPS, mm; ``engine.orient.to_patient``), and the
  object carries the source's Frame of Reference UID, so a viewer can overlay it on the CT;
* Patient and General/Patient Study modules are copied from the source (same patient, same study), the object
  gets its own series (UIDs given by the caller, so a re-sent delivery stores the same instance again);
* Manufacturing 3D Model module: Measurement Units Code Sequence = ``mm`` (UCUM);
* Enhanced General Equipment: manufacturer, model name, serial number and software version of bonemesh;
* Source Instance Sequence: the CT images it was built from (optional).

pydicom is imported inside the function (the engine's DICOM extra).
"""

from __future__ import annotations

import datetime as dt
import io
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.export.stl import to_stl

ENCAPSULATED_STL_STORAGE = "1.2.840.10008.5.1.4.1.1.104.3"
STL_MIME = "model/stl"
MANUFACTURER = "bonemesh"

# attributes copied from the source CT, by module (PS3.3 C.7.1.1 Patient, C.7.2.1 General Study, C.7.2.2 Patient
# Study); type 2 ones are written empty when the source lacks them
PATIENT_TYPE2 = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex")
PATIENT_OPTIONAL = (
    "IssuerOfPatientID",
    "IssuerOfPatientIDQualifiersSequence",
    "OtherPatientIDsSequence",
    "PatientBirthTime",
    "TypeOfPatientID",
    "QualityControlSubject",
    "PatientSpeciesDescription",
    "PatientSpeciesCodeSequence",
    "PatientBreedDescription",
    "PatientBreedCodeSequence",
    "BreedRegistrationSequence",
    "ResponsiblePerson",
    "ResponsiblePersonRole",
    "ResponsibleOrganization",
    "PatientComments",
    "PatientIdentityRemoved",
    "DeidentificationMethod",
    "DeidentificationMethodCodeSequence",
)
STUDY_TYPE2 = ("StudyDate", "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber")
STUDY_OPTIONAL = (
    "IssuerOfAccessionNumberSequence",
    "StudyDescription",
    "PhysiciansOfRecord",
    "NameOfPhysiciansReadingStudy",
    "ProcedureCodeSequence",
    "ReferencedStudySequence",
    "PatientAge",
    "PatientSize",
    "PatientWeight",
    "AdmittingDiagnosesDescription",
)


def to_encapsulated_stl(
    verts_zyx_mm: npt.NDArray[np.float32],
    faces: npt.NDArray[np.int32],
    source: Any,
    *,
    series_instance_uid: str,
    sop_instance_uid: str,
    software_version: str,
    created: dt.datetime,
    series_number: int = 9900,
    series_description: str = "bonemesh bone model (STL, mm)",
    device_serial_number: str = "bonemesh",
    source_instances: Sequence[tuple[str, str]] = (),
    source_series_uid: str | None = None,
    document_title: str = "bone surface model",
    instance_number: int = 1,
) -> bytes:
    """Encode a print model as an Encapsulated STL DICOM file (Part 10, Explicit VR Little Endian).

    Args:
        verts_zyx_mm: (V, 3) float32 vertices in (z, y, x) order, in mm, in the source's patient frame (LPS).
        faces: (F, 3) int32, outward with vertices taken in (x, y, z) order.
        source: a pydicom ``Dataset`` of the source CT (one image's header is enough); it must carry
            StudyInstanceUID and FrameOfReferenceUID.
        series_instance_uid: the new series' UID.
        sop_instance_uid: the object's UID.
        software_version: bonemesh's version (Software Versions).
        created: the content date and time (UTC).
        series_number: the new series' number.
        series_description: the new series' description.
        device_serial_number: Device Serial Number (type 1 in Enhanced General Equipment).
        source_instances: (SOP Class UID, SOP Instance UID) of the images the model was built from (each once).
        source_series_uid: their series (default: the ``source`` header's Series Instance UID).
        document_title: Document Title (a label job's segment name, so the archive lists each model by it).
        instance_number: the object's number in its series (a label job's models: 1, 2, ...).

    Returns:
        The DICOM file's bytes.

    Raises:
        ValueError: the source lacks its Study Instance UID or Frame of Reference UID (the model could not be
            placed beside it), or the mesh is empty.
    """
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence as DicomSequence

    for keyword in ("StudyInstanceUID", "FrameOfReferenceUID"):
        if not str(getattr(source, keyword, "") or ""):
            raise ValueError(f"Expected the source CT to carry {keyword}, got none: the model cannot be placed in it")
    if len(faces) == 0:
        raise ValueError("Expected a mesh with faces, got an empty mesh")
    stl = to_stl(verts_zyx_mm, faces, header="bonemesh model, patient LPS frame, mm")

    ds = Dataset()
    _patient_and_study(ds, source)
    # Encapsulated Document Series
    ds.Modality = "M3D"
    ds.SeriesInstanceUID = series_instance_uid
    ds.SeriesNumber = series_number
    ds.SeriesDescription = series_description
    # Frame of Reference: the source's, so the model overlays the CT
    ds.FrameOfReferenceUID = source.FrameOfReferenceUID
    ds.PositionReferenceIndicator = source.get("PositionReferenceIndicator", "")
    # General + Enhanced General Equipment
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = MANUFACTURER
    ds.DeviceSerialNumber = device_serial_number
    ds.SoftwareVersions = software_version
    _document(ds, stl, created, instance_number, document_title)
    if source_instances:
        _references(ds, source_instances, source_series_uid or source.SeriesInstanceUID)
    # Manufacturing 3D Model: the unit of the vertices
    unit = Dataset()
    unit.CodeValue = "mm"
    unit.CodingSchemeDesignator = "UCUM"
    unit.CodeMeaning = "mm"
    ds.MeasurementUnitsCodeSequence = DicomSequence([unit])
    # SOP Common
    ds.SOPClassUID = ENCAPSULATED_STL_STORAGE
    ds.SOPInstanceUID = sop_instance_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = ds.ContentDate, ds.ContentTime
    return _part10(ds, sop_instance_uid)


def _patient_and_study(ds: Any, source: Any) -> None:
    """The source's character set, Patient and General Study modules (type 2 kept, empty where the source lacks
    them)."""
    if "SpecificCharacterSet" in source:
        ds.SpecificCharacterSet = source.SpecificCharacterSet
    _copy(ds, source, PATIENT_TYPE2, empty=True)
    _copy(ds, source, PATIENT_OPTIONAL)
    ds.StudyInstanceUID = source.StudyInstanceUID
    _copy(ds, source, STUDY_TYPE2, empty=True)
    _copy(ds, source, STUDY_OPTIONAL)


def _document(ds: Any, stl: bytes, created: dt.datetime, instance_number: int, title: str) -> None:
    """The Encapsulated Document module: the STL, its title and the content's date and time."""
    from pydicom.sequence import Sequence as DicomSequence

    stamp_date, stamp_time = created.strftime("%Y%m%d"), created.strftime("%H%M%S")
    ds.InstanceNumber = instance_number
    ds.ContentDate, ds.ContentTime = stamp_date, stamp_time
    ds.AcquisitionDateTime = created.strftime("%Y%m%d%H%M%S")
    ds.BurnedInAnnotation = "NO"
    ds.DocumentTitle = title[:64]
    ds.ConceptNameCodeSequence = DicomSequence()
    ds.MIMETypeOfEncapsulatedDocument = STL_MIME
    body = stl if len(stl) % 2 == 0 else stl + b"\x00"  # OB values have even length; the length tag keeps the truth
    ds.EncapsulatedDocument = body
    ds.EncapsulatedDocumentLength = len(stl)


def _references(ds: Any, source_instances: Sequence[tuple[str, str]], series_uid: str) -> None:
    """The images the model was built from: Source Instance Sequence, and the same under their series (Common
    Instance Reference; all in this study)."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence as DicomSequence

    ds.SourceInstanceSequence = DicomSequence([_ref(c, i) for c, i in source_instances])
    series = Dataset()
    series.SeriesInstanceUID = series_uid
    series.ReferencedInstanceSequence = DicomSequence([_ref(c, i) for c, i in source_instances])
    ds.ReferencedSeriesSequence = DicomSequence([series])


def _part10(ds: Any, sop_instance_uid: str) -> bytes:
    """The dataset as a Part 10 file (Explicit VR Little Endian)."""
    from pydicom.dataset import FileMetaDataset
    from pydicom.filewriter import dcmwrite
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ENCAPSULATED_STL_STORAGE
    meta.MediaStorageSOPInstanceUID = sop_instance_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds.file_meta = meta
    buf = io.BytesIO()
    dcmwrite(buf, ds, enforce_file_format=True)
    return buf.getvalue()


def stl_of(dicom_bytes: bytes) -> bytes:
    """The STL file encapsulated in an Encapsulated STL object (its declared length, without the padding).

    Raises:
        ValueError: not an Encapsulated STL object.
    """
    import pydicom

    ds = pydicom.dcmread(io.BytesIO(dicom_bytes))
    if ds.get("SOPClassUID") != ENCAPSULATED_STL_STORAGE:
        raise ValueError(f"Expected SOP Class {ENCAPSULATED_STL_STORAGE}, got {ds.get('SOPClassUID')}")
    data = bytes(ds.EncapsulatedDocument)
    length = ds.get("EncapsulatedDocumentLength")
    return data[: int(length)] if length is not None else data


def _ref(class_uid: str, instance_uid: str) -> Any:
    from pydicom.dataset import Dataset

    ref = Dataset()
    ref.ReferencedSOPClassUID = class_uid
    ref.ReferencedSOPInstanceUID = instance_uid
    return ref


def _copy(ds: Any, source: Any, keywords: Sequence[str], *, empty: bool = False) -> None:
    for keyword in keywords:
        if keyword in source:
            ds[keyword] = source[keyword]
        elif empty:
            setattr(ds, keyword, "")
