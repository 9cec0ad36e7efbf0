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

from engine.errors import EngineError
from service.db import Database
from service.logsafe import safe_logger
from service.pacs.records import PacsRecords

log = safe_logger("bonemesh.worker")
MODEL_DCM = "model.dcm"


class SourceUnavailable(EngineError):
    """The job's DICOMweb source could not be fetched (server down, refused, or the series is empty)."""


def fetch_source(db: Database, job_id: str, upload: Path) -> None:
    """Fetch a DICOMweb job's series into ``upload`` (a folder) unless it is already there.

    Raises:
        SourceUnavailable: the server is not configured, unreachable, refuses, or returns no instance.
    """
    rec = PacsRecords(db).get(job_id)
    if rec is None or rec.source.get("kind") != "dicomweb" or upload.exists():
        return
    from service.pacs.config import get_pacs_settings
    from service.pacs.dicomweb import fetch_series

    name = rec.source["server"]
    server = get_pacs_settings().dicomweb_servers.get(name)
    if server is None:
        raise SourceUnavailable(f"DICOMweb server {name!r} is not configured on this worker")
    tmp = upload.parent / f".fetch-{uuid.uuid4().hex}"
    try:
        count = fetch_series(server, rec.source["study_uid"], rec.source["series_uid"], tmp)
        if count == 0:
            raise SourceUnavailable(f"DICOMweb server {name!r} returned no instance of the series")
        tmp.rename(upload)
    except SourceUnavailable:
        raise
    except Exception as exc:
        raise SourceUnavailable(f"could not retrieve the series from DICOMweb server {name!r}: {exc}") from exc
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("job %s: %d instances retrieved with WADO-RS from %s", job_id, count, name)


def write_dicom_model(db: Database, job_id: str, upload: Path, staged: Path) -> dict[str, Path]:
    """Write ``model.dcm`` (Encapsulated STL of ``staged/model.stl``) for a PACS job; {} for other jobs.

    Nothing is written when the source lacks a Frame of Reference UID (the delivery then says why).
    """
    rec = PacsRecords(db).get(job_id)
    stl_path = staged / "model.stl"
    if rec is None or not stl_path.is_file():
        return {}
    from engine.export.dicom_stl import to_encapsulated_stl
    from engine.export.stl import from_stl

    source, instances = _source_header(upload, rec.source.get("series_uid"))
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
        source_instances=instances,
    )
    path = staged / MODEL_DCM
    path.write_bytes(data)
    return {MODEL_DCM: path}


def _source_header(upload: Path, series_uid: str | None) -> tuple[Any, list[tuple[str, str]]]:
    """One image header of the source series and the (SOP class, SOP instance) of each of its images."""
    import pydicom

    first = None
    instances = []
    files = sorted(p for p in upload.rglob("*") if p.is_file()) if upload.is_dir() else []
    for path in files:
        try:
            ds = pydicom.dcmread(path, stop_before_pixels=True)
        except Exception:
            continue
        if series_uid and ds.get("SeriesInstanceUID") != series_uid:
            continue
        if first is None:
            first = ds
        instances.append((str(ds.SOPClassUID), str(ds.SOPInstanceUID)))
    return first, instances


def _version() -> str:
    try:
        return importlib.metadata.version("bonemesh")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


__all__ = ["MODEL_DCM", "SourceUnavailable", "fetch_source", "write_dicom_model"]
