"""The worker's part of PACS jobs: fetch a DICOMweb series before loading (a SEG with the CT series it references),
and write the model as Encapsulated STL (``model.dcm``), or a label job's models as one Encapsulated STL per label
(``labels.dcm.zip``), beside the other outputs. Each does nothing for an uploaded job (no ``pacs_jobs`` row).

The Encapsulated STL is built from the published-to-be ``model.stl`` (already in the source's patient frame, LPS
mm) and the header of one source image; the source image's identity stays inside the DICOM object, which goes back
to the hospital's archive, and never reaches the report or a log.
"""

from __future__ import annotations

import datetime as dt
import importlib.metadata
import shutil
import uuid
from pathlib import Path
from typing import Any

from core.db import Database
from core.logsafe import safe_logger
from core.pacs.records import PacsRecords, is_uid, label_sop_uid
from core.pacs.routing import REFERENCE_FOLDER
from engine.job import LABELS_DCM, LABELS_ZIP, MODEL_DCM, PRINT_STL, Volume

log = safe_logger("bonemesh.worker")


class JobSourceError(Exception):
    """Base of the worker's errors about a job's source (not the engine's: the scan is never read). Each has its
    error code in ``worker.tasks._explain``:

    JobSourceError
    ├── SourceUnavailable       source_unavailable: the DICOMweb series could not be fetched
    │   └── SourceIncomplete    source_incomplete: the server returned fewer instances than it lists
    └── UncheckedSource         incomplete_series: the series was not checked complete, so no model for the PACS
    """


class SourceUnavailable(JobSourceError):
    """The job's DICOMweb source could not be fetched (server down, refused, or the series is empty)."""


class SourceIncomplete(SourceUnavailable):
    """The DICOMweb server returned fewer instances of the series than it lists (after every retry): nothing is
    reconstructed from the rest, so nothing is delivered.

    Attributes:
        server: the server's name in the settings.
        expected, retrieved: the counts; ``missing``: the SOP Instance UIDs still missing.
    """

    def __init__(self, server: str, expected: int, retrieved: int, missing: tuple[str, ...]) -> None:
        super().__init__(
            f"the DICOMweb server {server!r} returned {retrieved} of {expected} instances of the series "
            f"(missing: {len(missing)})"
        )
        self.server, self.expected, self.retrieved, self.missing = server, expected, retrieved, missing


def fetch_source(db: Database, job_id: str, upload: Path) -> None:
    """Fetch a DICOMweb job's series into ``upload`` (a folder) unless it is already there: every instance the
    server lists, or nothing (the instances are fetched into a hidden folder renamed ``upload`` once complete).

    Raises:
        SourceIncomplete: an instance the server lists could not be retrieved.
        SourceUnavailable: the server is not configured, unreachable, refuses, or lists no instance.
    """
    rec = PacsRecords(db).get(job_id)
    if rec is None or rec.source.get("kind") != "dicomweb" or upload.exists():
        return
    from core.pacs.config import get_pacs_settings
    from core.pacs.dicomweb import DicomwebError, SeriesIncomplete, fetch_series

    name = rec.source["server"]
    server = get_pacs_settings().dicomweb_servers.get(name)
    if server is None:
        raise SourceUnavailable(f"DICOMweb server {name!r} is not configured on this worker")
    tmp = upload.parent / f".fetch-{uuid.uuid4().hex}"
    try:
        got = fetch_series(server, rec.source["study_uid"], rec.source["series_uid"], tmp)
        reference = _seg_reference(tmp)
        if reference is not None:  # a SEG: the CT series it was drawn on too, whole, into reference/
            log.info("job %s: the series is a SEG; fetching the series it references", job_id)
            _fetch_reference(server, name, rec.source["study_uid"], reference, tmp / REFERENCE_FOLDER)
        tmp.rename(upload)
    except SeriesIncomplete as exc:
        r = exc.result
        log.warning(
            "job %s: %d of %d instances retrieved with WADO-RS from %s (%d missing, %d one by one); job failed",
            job_id, r.retrieved, r.expected, name, len(r.missing), r.one_by_one,
        )  # fmt: skip
        raise SourceIncomplete(name, r.expected, r.retrieved, r.missing) from None
    except DicomwebError as exc:
        raise SourceUnavailable(f"could not retrieve the series from DICOMweb server {name!r}: {exc}") from None
    except SourceUnavailable:  # the SEG's referenced series: told as such
        raise
    except Exception as exc:  # the cause stays: a full disk is told as such (_explain)
        raise SourceUnavailable(
            f"could not retrieve the series from DICOMweb server {name!r} ({type(exc).__name__})"
        ) from exc
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info(
        "job %s: %d of %d instances retrieved with WADO-RS from %s (%d one by one, %d repeated, %d unlisted; "
        "transfer syntaxes %s)",
        job_id, got.retrieved, got.expected, name, got.one_by_one, got.duplicates, got.unlisted,
        ", ".join(f"{uid} x{n}" for uid, n in sorted(got.transfer_syntaxes.items())),
    )  # fmt: skip


def _seg_reference(folder: Path) -> str | None:
    """The series a fetched SEG references (None when the folder holds no SEG)."""
    seg = _seg_header(folder)
    if seg is None:
        return None
    from engine.job import referenced_series

    wanted = referenced_series(seg)
    if not wanted or not is_uid(wanted):
        raise SourceUnavailable(
            "the SEG names no well-formed referenced series (ReferencedSeriesSequence) to place it on"
        )
    return wanted


def _fetch_reference(server: Any, name: str, study_uid: str, series_uid: str, folder: Path) -> None:
    """The SEG's CT series from the same server and study, every instance or nothing (as ``fetch_source``).

    Raises:
        SeriesIncomplete, DicomwebError: as ``fetch_series`` (told by ``fetch_source``).
    """
    from core.pacs.dicomweb import DicomwebError, fetch_series

    try:
        fetch_series(server, study_uid, series_uid, folder)
    except DicomwebError as exc:
        raise SourceUnavailable(
            f"the SEG's referenced series {series_uid} could not be retrieved from DICOMweb server {name!r}: {exc}"
        ) from None


class UncheckedSource(JobSourceError):
    """The volume's source was not checked complete, so no model is made for the PACS."""


def write_dicom_model(db: Database, job_id: str, upload: Path, staged: Path, volume: Volume) -> dict[str, Path]:
    """Write ``model.dcm`` (Encapsulated STL of ``staged/model.stl``) for a PACS job; {} for other jobs.

    The object references the source series and exactly the images ``volume`` was built from
    (``Volume.instances``: the series after the completeness checks, duplicates dropped). Nothing is written when
    the source lacks a Frame of Reference UID (the delivery then says why).

    Raises:
        UncheckedSource: the volume's source was not checked complete; such a model never goes to a PACS.
    """
    rec = PacsRecords(db).get(job_id)
    stl_path = staged / PRINT_STL
    if rec is None or not stl_path.is_file():
        return {}
    _require_whole(volume.source.get("completeness"), bool(volume.instances))
    from engine.job import from_stl, to_encapsulated_stl

    used = list(dict.fromkeys((cls, uid) for cls, uid, _frame in volume.instances))  # a multi-frame image once
    source = _source_header(upload, volume.source.get("series_uid"), used[0][1])
    if source is None or "FrameOfReferenceUID" not in source:
        log.warning("job %s: the source series has no Frame of Reference UID; no model.dcm", job_id)
        return {}
    verts, faces = from_stl(stl_path.read_bytes())
    data = to_encapsulated_stl(
        verts,
        faces,
        source,
        series_instance_uid=rec.result_series_uid,
        sop_instance_uid=rec.result_sop_uid,
        software_version=_version(),
        created=dt.datetime.now(dt.UTC),
        source_instances=used,
        source_series_uid=volume.source.get("series_uid"),
    )
    path = staged / MODEL_DCM
    path.write_bytes(data)
    return {MODEL_DCM: path}


def _require_whole(completeness: dict[str, Any] | None, has_images: bool, what: str = "source series") -> None:
    """Raise ``UncheckedSource`` unless the completeness checks ran and found the series whole."""
    done = completeness or {}
    if not (done.get("checked") and done.get("complete")) or not has_images:
        raise UncheckedSource(
            f"the {what} was not checked complete (or names no DICOM images), so no model is made for the PACS; "
            "send the whole series"
        )


def write_dicom_labels(
    db: Database, job_id: str, upload: Path, staged: Path, report: dict[str, Any], volume: Volume | None = None
) -> dict[str, Path]:
    """Write ``labels.dcm.zip`` for a PACS label job: one Encapsulated STL per label (``labels.zip``'s STL, LPS mm),
    each named by its label (Document Title, Series Description), all in the job's one result series; {} for
    other jobs.

    A SEG's models reference the SEG and take its patient, study and Frame of Reference (the SEG's, which is its
    CT's); they are made only when the CT the SEG was placed on was checked whole. A CT's ``pieces`` (``volume``)
    reference the images they were built from, as ``model.dcm`` does.

    Raises:
        UncheckedSource: the CT was not checked complete; such models never go to a PACS.
    """
    rec = PacsRecords(db).get(job_id)
    zipped = staged / LABELS_ZIP
    if rec is None or not zipped.is_file():
        return {}
    if volume is not None:  # a CT's pieces
        _require_whole(volume.source.get("completeness"), bool(volume.instances))
        used = list(dict.fromkeys((cls, uid) for cls, uid, _frame in volume.instances))
        source = _source_header(upload, volume.source.get("series_uid"), used[0][1])
        series_uid = volume.source.get("series_uid")
    else:  # a SEG on its CT
        reference = (report.get("source") or {}).get("reference") or {}
        _require_whole(reference.get("completeness"), bool(reference.get("images")), "SEG's referenced CT series")
        source = _seg_header(upload)
        used = [] if source is None else [(str(source.SOPClassUID), str(source.SOPInstanceUID))]
        series_uid = None if source is None else str(source.SeriesInstanceUID)
    if source is None or "FrameOfReferenceUID" not in source:
        log.warning("job %s: the source has no Frame of Reference UID; no %s", job_id, LABELS_DCM)
        return {}
    return {LABELS_DCM: _label_objects(rec, job_id, zipped, report["labels"], source, used, series_uid, staged)}


def _label_objects(
    rec: Any, job_id: str, zipped: Path, rows: list[dict[str, Any]], source: Any, used: Any, series: Any, staged: Path
) -> Path:
    """``labels.dcm.zip`` in ``staged``: ``<n>-<name>.dcm`` per label row, in the rows' order."""
    import zipfile

    from engine.job import from_stl, to_encapsulated_stl

    created, version = dt.datetime.now(dt.UTC), _version()
    path = staged / LABELS_DCM
    with zipfile.ZipFile(zipped) as stls, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as out:
        for n, row in enumerate(rows, start=1):
            verts, faces = from_stl(stls.read(row["file"]))
            data = to_encapsulated_stl(
                verts,
                faces,
                source,
                series_instance_uid=rec.result_series_uid,
                sop_instance_uid=label_sop_uid(job_id, int(row["value"])),
                software_version=version,
                created=created,
                series_description="bonemesh label models (STL, mm)",
                source_instances=used,
                source_series_uid=series,
                document_title=str(row["name"]),
                instance_number=n,
            )
            out.writestr(f"{n:04d}-{Path(row['file']).stem}.dcm", data)
    return path


def _seg_header(upload: Path) -> Any:
    """The header of the SEG among a job's files (the first, by name), or None."""
    import pydicom

    from engine.job import is_seg_file

    files = sorted(p for p in upload.rglob("*") if p.is_file()) if upload.is_dir() else [upload]
    seg = next((path for path in files if is_seg_file(path)), None)
    return None if seg is None else pydicom.dcmread(seg, stop_before_pixels=True)


def _source_header(upload: Path, series_uid: str | None, sop_uid: str) -> Any:
    """The header of the source image ``sop_uid`` (of series ``series_uid``), else of any image of the series;
    None when there is none."""
    import pydicom

    fallback = None
    files = sorted(p for p in upload.rglob("*") if p.is_file()) if upload.is_dir() else [upload]
    for path in files:
        try:
            ds = pydicom.dcmread(path, stop_before_pixels=True)
        except Exception:
            continue
        if series_uid and ds.get("SeriesInstanceUID") != series_uid:
            continue
        if ds.get("SOPInstanceUID") == sop_uid:
            return ds
        fallback = fallback if fallback is not None else ds
    return fallback


def _version() -> str:
    try:
        return importlib.metadata.version("bonemesh")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


__all__ = [
    "LABELS_DCM",
    "MODEL_DCM",
    "JobSourceError",
    "SourceIncomplete",
    "SourceUnavailable",
    "UncheckedSource",
    "fetch_source",
    "write_dicom_labels",
    "write_dicom_model",
]
