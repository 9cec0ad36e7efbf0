"""The worker's part of PACS jobs: fetch a DICOMweb series before loading, and write the model as Encapsulated STL
(``model.dcm``) beside the other outputs. Both do nothing for an uploaded job (no ``pacs_jobs`` row).

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
from core.pacs.records import PacsRecords
from engine.export.files import MODEL_DCM, PRINT_STL
from engine.types import Volume

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
    completeness = volume.source.get("completeness") or {}
    if not (completeness.get("checked") and completeness.get("complete")) or not volume.instances:
        raise UncheckedSource(
            "the source series was not checked complete (or names no DICOM images), so no model is made for the "
            "PACS; send the whole series"
        )
    from engine.export.dicom_stl import to_encapsulated_stl
    from engine.export.stl import from_stl

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
    "MODEL_DCM",
    "JobSourceError",
    "SourceIncomplete",
    "SourceUnavailable",
    "UncheckedSource",
    "fetch_source",
    "write_dicom_model",
]
