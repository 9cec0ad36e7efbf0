"""The API's PACS part: ``POST /v1/jobs`` with a JSON body naming a DICOMweb series. The request only records the
job (with its ``pacs_jobs`` row) and enqueues it; the worker fetches the series with WADO-RS (``worker.pacs``), so a
slow or large PACS never holds an API thread."""

from __future__ import annotations

import json
from functools import cache
from typing import Any

import anyio
from fastapi import Request
from pydantic import ValidationError

from core.db import Database, Job
from core.pacs.config import get_pacs_settings
from core.pacs.records import PacsRecords
from core.storage import version_of
from engine.export.files import LABELS_DCM, MODEL_DCM
from service.pacs.models import SourceJobCreate
from service.problems import Problem

MAX_BODY = 64 << 10


def is_json(request: Request) -> bool:
    """Whether the request body is JSON (a source job) rather than multipart (an upload)."""
    return request.headers.get("content-type", "").split(";")[0].strip().lower() == "application/json"


@cache
def records_of(db: Database) -> PacsRecords:
    """The PACS records of a database (the table made once per process)."""
    return PacsRecords(db)


def job_view(db: Database, job: Job) -> dict[str, Any]:
    """``source`` and ``delivery`` of the job resource ({} for an upload)."""
    return records_of(db).view(job)


def redeliver(svc: Any, job: Job) -> None:
    """Queue a finished PACS job's model for sending again (``POST /v1/jobs/{id}/deliver``; idempotent).

    Raises:
        Problem: 409 when the job has not succeeded, has no PACS destination, or has no model to send.
    """
    if job.state != "succeeded":
        raise Problem(409, f"job {job.id} is {job.state}: only a succeeded job's model can be delivered")
    if all(svc.storage.output(job.id, name, version_of(job)) is None for name in (MODEL_DCM, LABELS_DCM)):
        raise Problem(
            409,
            f"job {job.id} has no {MODEL_DCM} or {LABELS_DCM} to deliver (it came from an upload, or its source had "
            "no Frame of Reference)",
        )
    if not records_of(svc.db).redeliver(job.id):
        raise Problem(409, f"job {job.id} has no PACS destination to deliver to")


async def read_source(request: Request) -> SourceJobCreate:
    """The JSON body naming a DICOMweb series, validated (422 naming the field; 413 past :data:`MAX_BODY`)."""
    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_BODY:
            raise Problem(413, f"a JSON job request is limited to {MAX_BODY:,} bytes")
    try:
        spec = SourceJobCreate.model_validate(json.loads(body or b"null"))
    except (ValueError, RecursionError) as exc:
        errs = exc.errors() if isinstance(exc, ValidationError) else []
        fields = [{"field": ".".join(str(p) for p in e["loc"]), "message": e["msg"]} for e in errs]
        detail = "; ".join(f"{f['field']}: {f['message']}" for f in fields) or "the body is not valid JSON"
        raise Problem(422, detail, errors=fields or None) from None
    return spec


async def create_source_job(svc: Any, who: str, spec: SourceJobCreate) -> Job:
    """Record the job of a validated body (``read_source``) and send its message (``svc``: the app's Services)."""
    try:
        spec.params.job_spec()
    except ValueError as exc:
        raise Problem(422, f"params: {exc}", errors=[{"field": "params", "message": str(exc)}]) from None
    source = spec.source.dicomweb
    servers = get_pacs_settings().dicomweb_servers
    if source.server not in servers:
        known = ", ".join(sorted(servers)) or "none is configured"
        raise Problem(
            422,
            f"source.dicomweb.server: unknown DICOMweb server {source.server!r} ({known})",
            errors=[{"field": "source.dicomweb.server", "message": "unknown server"}],
        )

    def record() -> Job:
        job = Job(
            id=Database.new_id(),
            owner=who,
            state="queued",
            params=spec.params.record(),
            upload_name=f"DICOMweb series from {source.server}"[:255],
            upload_bytes=0,
        )
        dest = {"kind": "dicomweb", "server": source.server} if spec.deliver else None
        records_of(svc.db).create_job(job, {"kind": "dicomweb", **source.model_dump()}, dest)
        svc.enqueue(job.id)
        return svc.db.get(job.id) or job

    return await anyio.to_thread.run_sync(record)
