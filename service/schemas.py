"""Response models of the API (the job resource and its list) and the OpenAPI documents of the upload body and
of a download."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from core.params import JobParams
from engine.export.files import FILES
from service.pacs.models import Delivery, SourceJobCreate


class JobError(BaseModel):
    """Why a job failed."""

    code: str = Field(
        description="machine-readable reason: bad_input, no_spacing, no_surface, print_check, storage_full, "
        "too_large, time_limit, worker_lost, source_unavailable (DICOMweb series not retrievable), "
        "source_incomplete (the DICOMweb server returned fewer instances than it lists), incomplete_series (a slice "
        "missing, two different images at one position, or too few images: nothing reconstructed), internal_error"
    )
    message: str = Field(description="what went wrong, in words")


class OutputFile(BaseModel):
    """One output of a succeeded job, with its signed download link (the files are those of engine/export/files.py)."""

    name: str
    kind: str = Field(description=", ".join(f"{f.kind} ({f.name})" for f in FILES.values()))
    purpose: str = Field(description="what the file is for, in words (the page shows it)")
    media_type: str
    bytes: int
    triangles: int | None
    url: str = Field(description="signed download link; works without the API key until expires_at")
    expires_at: dt.datetime


class WebhookAttempt(BaseModel):
    """One delivery of a job's webhook."""

    at: dt.datetime
    status: int | None = Field(description="the receiver's HTTP status; null when no answer came")
    error: str | None = Field(default=None, description="why the attempt failed, when it did")


class WebhookOut(BaseModel):
    """The job's callback and its deliveries (signed as Standard Webhooks; see GET /v1/webhook-secret)."""

    url: str
    state: Literal["pending", "delivered", "failed"] = Field(
        description="pending (not yet finished, or retrying), delivered (2xx), failed (retries used up)"
    )
    attempts: list[WebhookAttempt]


class WebhookSecret(BaseModel):
    """The secret this API key's webhooks are signed with (Standard Webhooks ``whsec_`` form)."""

    secret: str


class AttemptOut(BaseModel):
    """One attempt at a job: the worker that ran it, on which host, and how it ended."""

    number: int = Field(description="1 for the first attempt; a job re-run after its worker stopped has more")
    worker: str = Field(description="the worker's name (its Celery node name, unique per worker process)")
    host: str = Field(description="the host the worker ran on")
    started_at: dt.datetime
    finished_at: dt.datetime | None
    outcome: Literal["running", "succeeded", "failed", "cancelled", "lost", "outage"] = Field(
        description="running (not ended yet), succeeded, failed, cancelled, lost (its worker stopped, killed or "
        "silent, and the job went to another attempt), or outage (the database or the file store was unreachable: "
        "the job went back to the queue, and this attempt does not count against the job's limit)"
    )


class JobOut(BaseModel):
    """A job: its state, progress, parameters and, once succeeded, its outputs."""

    id: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    stage: str | None
    progress: float = Field(ge=0, le=100)
    upload_name: str = Field(description="the uploaded file's name, control characters escaped")
    upload_bytes: int
    params: dict[str, Any]
    attempts: int
    runs: list[AttemptOut] = Field(
        default_factory=list, description="each attempt (``attempts`` counts them), oldest first: worker, host, times"
    )
    created_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None
    error: JobError | None
    outputs: list[OutputFile] | None
    webhook: WebhookOut | None = Field(default=None, description="the callback and its delivery attempts, if any")
    source: dict[str, Any] | None = Field(
        default=None, description="PACS jobs only: C-STORE sender or DICOMweb server, Study and Series Instance UIDs"
    )
    delivery: Delivery | None = Field(default=None, description="PACS jobs only: the model sent back as DICOM")


class JobList(BaseModel):
    """A page of the key's jobs, newest first."""

    items: list[JobOut]
    total: int
    limit: int
    offset: int


class UploadOptions(BaseModel):
    """How this service takes uploads (``GET /v1/upload-options``): whether the client may send the scan straight
    to the store (S3 storage) or must upload it through ``POST /v1/jobs``."""

    direct: bool = Field(description="true: POST /v1/uploads hands out links to the store; false: use POST /v1/jobs")
    reason: str | None = Field(description="why direct uploads are off, when they are")
    max_upload_bytes: int = Field(description="the largest scan accepted, either way")
    parallel_parts: int = Field(description="how many parts a client should send at once (the page sends 4)")


class DirectUploadCreate(BaseModel):
    """A scan the client is about to send straight to the store, and the job it is for."""

    model_config = ConfigDict(extra="forbid")

    filename: str = Field(min_length=1, max_length=1024, description="the archive's name (zip, tar, tar.gz, ...)")
    size: int = Field(ge=1, le=2**53, description="its exact size in bytes")
    params: JobParams = Field(default_factory=JobParams, description="the job's parameters, as for POST /v1/jobs")
    callback_url: str | None = Field(
        default=None, max_length=2048, description="https or http URL POSTed the job when it ends (as for /v1/jobs)"
    )


class UploadPart(BaseModel):
    """Where to send one part: ``PUT url`` with the part's bytes (``offset`` to ``offset + bytes``) and exactly
    ``headers`` (SigV4-presigned; Content-Type is not signed, so any the client adds is fine)."""

    number: int
    offset: int
    bytes: int
    method: Literal["PUT"] = "PUT"
    url: str
    headers: dict[str, str] = Field(description="every header the store needs besides those HTTP sends itself")


class DirectUploadOut(BaseModel):
    """A direct upload begun: send each part, keep each answer's ETag, then POST the complete link."""

    id: str = Field(description="the upload's id; also the id of the job it becomes")
    part_bytes: int = Field(description="every part is this long but the last")
    parts: list[UploadPart]
    expires_at: dt.datetime = Field(description="the links stop working then, and an incomplete upload is aborted")
    complete_url: str
    abort_url: str


class CompletedPart(BaseModel):
    model_config = ConfigDict(extra="forbid")

    number: int = Field(ge=1, le=10_000)
    etag: str = Field(min_length=1, max_length=256, description="the ETag header of the part's PUT answer")


class DirectUploadComplete(BaseModel):
    """The parts sent; ``parts`` may be left out (a browser may not read the store's ETag header): the API then
    takes the parts the store holds, after checking they add up to the declared size."""

    model_config = ConfigDict(extra="forbid")

    parts: list[CompletedPart] | None = Field(default=None, max_length=10_000)


class Readiness(BaseModel):
    """Whether the database, Redis and storage answer (``/readyz``)."""

    status: Literal["ready", "not ready"]
    checks: dict[str, str] = Field(description="'ok' or 'unreachable: <reason>' for each dependency")


# the multipart body of POST /v1/jobs (read by service.uploads, not by FastAPI)
UPLOAD_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": ["file"],
                "additionalProperties": False,
                "properties": {
                    "file": {
                        "type": "string",
                        "format": "binary",
                        "description": "zip, tar or tar.gz of 2-D slices, or a DICOM series as a zip",
                    },
                    "callback_url": {
                        "type": "string",
                        "format": "uri",
                        "description": "https or http URL POSTed the job (signed, Standard Webhooks) when it ends",
                    },
                    "params": {
                        "type": "string",
                        "description": "JSON object of JobParams (iso or preset, spacing, reduction, orient, "
                        "preprocess, body, islands...); all optional",
                        "contentMediaType": "application/json",
                        "contentSchema": {"$ref": "#/components/schemas/JobParams"},
                    },
                },
            },
            "encoding": {"params": {"contentType": "application/json"}},
        },
        "application/json": {"schema": {"$ref": "#/components/schemas/SourceJobCreate"}},  # a DICOMweb series
    },
}
DOWNLOAD_CONTENT = {
    "content": {
        **{
            media: {"schema": {"type": "string", "format": "binary"}}
            for media in dict.fromkeys(f.media_type for f in FILES.values() if f.media_type != "application/json")
        },
        "application/json": {"schema": {"type": "object"}},
    },
    "description": "the file (report.json is JSON, the models are binary)",
}


def add_job_params(schema: dict[str, Any]) -> dict[str, Any]:
    """Put ``JobParams`` and its groups in the document's components (the upload's ``params`` part refers to it)."""
    doc = JobParams.model_json_schema(ref_template="#/components/schemas/{model}")
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.update(doc.pop("$defs", {}))
    components["JobParams"] = doc
    source = SourceJobCreate.model_json_schema(ref_template="#/components/schemas/{model}")
    components.update({k: v for k, v in source.pop("$defs", {}).items() if k not in components})
    components["SourceJobCreate"] = source
    return schema
