"""The job resource: create (upload), list, read, cancel, delete, re-orient; and the key's webhook secret (its own
router, ``webhooks_router``: under the webhooks tag only, so /docs lists it once)."""

from __future__ import annotations

import datetime as dt
import json
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import JSONResponse, Response

from core.db import Job, utcnow
from core.faults import RETRY_AFTER_SECONDS
from core.params import OrientJobParams
from core.storage import version_of
from engine.defect.params import DEFECT_REORIENT
from service import headers as hdr
from service import idempotency
from service.deps import BaseUrlDep, OwnerDep, ServicesDep
from service.idempotency import KeyHeader
from service.intake import FULL, fingerprint_of, receive
from service.pacs import api as pacs_api
from service.pacs.models import SourceJobCreate
from service.problems import Problem
from service.problems import problems as errors
from service.schemas import UPLOAD_BODY, JobList, JobOut, WebhookSecret
from service.services import Services
from service.webhooks import key_secret

router = APIRouter(prefix="/v1", tags=["jobs"])
webhooks_router = APIRouter(prefix="/v1", tags=["webhooks"])
callbacks = APIRouter(tags=["webhooks"])  # what the service sends: the OpenAPI document's ``webhooks`` (3.1)
MULTIPART_SLACK = 1 << 20  # multipart headers and boundaries around the file
MAX_OFFSET = 2**31 - 1
KEYED = errors(401, d401="missing or unknown API key")


def _job(svc: Services, job_id: str, who: str) -> Job:
    job = svc.db.get(job_id, who)
    if job is None:
        raise Problem(404, f"no job {job_id} for this API key")
    return job


@router.post(
    "/jobs",
    status_code=202,
    response_model=JobOut,
    summary="upload a scan (multipart) or name a DICOMweb series (JSON), and start a reconstruction",
    responses={
        202: {"description": "the job, queued (or the one its Idempotency-Key made)", "headers": hdr.CREATED},
        **KEYED,
        **errors(
            400,
            413,
            415,
            422,
            507,
            d400="malformed or incomplete multipart body, or a part sent twice",
            d413="the upload is larger than the limit",
            d415="not multipart, or not an archive bonemesh reads",
            d422="invalid params or callback_url, an archive that cannot be a scan, or an Idempotency-Key used with "
            "another request (idempotency_key_reused)",
            d507="the data volume cannot hold the upload (nothing was kept)",
        ),
        409: {
            "description": "a request with this Idempotency-Key is still being carried out (idempotency_key_in_use)",
            "headers": hdr.IN_USE,
        },
    },
    openapi_extra={"requestBody": UPLOAD_BODY},
)
async def create_job(
    request: Request, who: OwnerDep, svc: ServicesDep, base: BaseUrlDep, idempotency_key: KeyHeader = None
) -> Response:
    limit = svc.settings.max_upload_bytes
    declared = request.headers.get("content-length")
    size = int(declared) if declared and declared.isdigit() and len(declared) < 20 else None
    if size is not None and size > limit + MULTIPART_SLACK:
        raise Problem(413, f"the upload ({size:,} bytes) is over the limit of {limit:,} bytes")
    if idempotency_key is None:
        job, _ = await _create(request, svc, who, base, size)
        return created(svc, job, base)
    found = await svc.in_upload_thread(idempotency.reserve, svc, who, idempotency.JOBS, idempotency_key)
    if isinstance(found, idempotency.Hold):
        job, fingerprint = await idempotency.held(found, _create(request, svc, who, base, size, found))
        await svc.in_upload_thread(found.finish, fingerprint, job.id, 202)
        return created(svc, job, base)
    if pacs_api.is_json(request):
        fingerprint = _source_print(await pacs_api.read_source(request))
    else:
        fingerprint = await fingerprint_of(request, svc, limit)
    job = _job(svc, idempotency.replayed(found, fingerprint), who)
    return created(svc, job, base, found.status_code or 202, replayed=True)


def created(svc: Services, job: Job, base: str, status: int = 202, *, replayed: bool = False) -> Response:
    """The answer to a job's creation: the job, its ``Location`` (and ``Idempotent-Replayed`` when sent again)."""
    headers = {"Location": f"/v1/jobs/{job.id}"}
    if replayed:
        headers[idempotency.REPLAYED] = "true"
    return JSONResponse(svc.job_out(job, base).model_dump(mode="json"), status_code=status, headers=headers)


def _source_print(spec: SourceJobCreate) -> str:
    return idempotency.canonical({"kind": "dicomweb", **spec.model_dump(mode="json")})


async def _create(
    request: Request, svc: Services, who: str, base: str, size: int | None, hold: idempotency.Hold | None = None
) -> tuple[Job, str]:
    """Make the job (a DICOMweb series, or an upload) and, under an Idempotency-Key (``hold``), its request's
    fingerprint (else ""): an upload's is the SHA-256 of its bytes (1.7 GB/s on this machine: 0.7 s of a 1 GB upload's
    write thread), not spent where no key will compare it."""
    if pacs_api.is_json(request):  # a DICOMweb series instead of a file
        spec = await pacs_api.read_source(request)
        return await pacs_api.create_source_job(svc, who, spec), _source_print(spec)
    free = await svc.in_upload_thread(svc.storage.free_bytes)
    if size is not None and free is not None and size > free:
        raise Problem(507, f"{FULL} ({size:,} bytes sent, {free:,} free)")
    fingerprint = idempotency.UploadPrint() if hold is not None else None
    async with svc.active_uploads:
        job = await receive(request, svc, who, svc.settings.max_upload_bytes, base, hold=hold, fingerprint=fingerprint)
    return job, fingerprint.hexdigest() if fingerprint is not None else ""


@router.get("/jobs", response_model=JobList, summary="your jobs, newest first", responses=KEYED)
def list_jobs(
    who: OwnerDep,
    svc: ServicesDep,
    base: BaseUrlDep,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
) -> JobList:
    rows, total = svc.db.list(who, limit, offset)
    return JobList(items=[svc.job_out(j, base) for j in rows], total=total, limit=limit, offset=offset)


@router.get(
    "/jobs/{job_id}",
    response_model=JobOut,
    summary="a job (poll it: If-None-Match with its ETag gives 304 while nothing changed; Retry-After: when to ask)",
    responses={200: {"headers": hdr.JOB_HEADERS}, 304: hdr.NOT_MODIFIED, **KEYED, **errors(404)},
)
def get_job(
    job_id: str,
    who: OwnerDep,
    svc: ServicesDep,
    base: BaseUrlDep,
    if_none_match: Annotated[
        str | None, Header(description="the ETag of the job seen last: 304 (no body) while it is unchanged")
    ] = None,
) -> Response:
    job = _job(svc, job_id, who)
    body = svc.job_out(job, base).model_dump(mode="json")
    etag = hdr.job_etag(body, svc.settings.url_ttl_seconds)
    sent = hdr.job_headers(job, etag)
    if hdr.etag_matches(if_none_match, etag):
        return Response(status_code=304, headers=sent)
    return JSONResponse(body, headers=sent)


@router.post(
    "/jobs/{job_id}/cancel",
    response_model=JobOut,
    summary="cancel a queued or running job (the record stays, as cancelled; its files are removed)",
    responses={**KEYED, **errors(404, 409, d409="the job has already finished")},
)
def cancel_job(job_id: str, who: OwnerDep, svc: ServicesDep, base: BaseUrlDep) -> JobOut:
    job = _job(svc, job_id, who)
    if job.state != "cancelled":
        if not svc.db.cancel(job_id):
            raise Problem(409, f"job {job_id} has already {job.state}; delete it to remove it and its files")
        svc.storage.delete_job(job_id)
    return svc.job_out(_job(svc, job_id, who), base)


@router.post(
    "/jobs/{job_id}/deliver",
    status_code=202,
    response_model=JobOut,
    summary="send a finished PACS job's model to its destination again (the same UIDs: the PACS keeps one copy)",
    responses={**KEYED, **errors(404, 409, d409="the job has not succeeded, or has no model or destination")},
)
def deliver_job(job_id: str, who: OwnerDep, svc: ServicesDep, base: BaseUrlDep) -> JobOut:
    pacs_api.redeliver(svc, _job(svc, job_id, who))
    return svc.job_out(_job(svc, job_id, who), base)


@router.delete(
    "/jobs/{job_id}",
    status_code=204,
    summary="delete a job and its files (a running one is stopped); afterwards the job answers 404",
    responses={**KEYED, **errors(404)},
)
def delete_job(job_id: str, who: OwnerDep, svc: ServicesDep) -> Response:
    _job(svc, job_id, who)
    svc.db.delete(job_id)
    svc.storage.delete_job(job_id)
    return Response(status_code=204)


@router.post(
    "/jobs/{job_id}/orient",
    status_code=202,
    response_model=JobOut,
    summary="place a finished image-stack job's model in another orientation: every output is written again in the "
    "corrected frame (no reconstruction) and published at once; the job shows stage 'orienting' meanwhile",
    responses={
        **KEYED,
        **errors(
            400,
            404,
            409,
            422,
            503,
            d400="the body is not valid JSON",
            d409="the job has not succeeded, is being re-oriented, is a DICOM series (placed by its headers) or has a "
            "defect template (its side and measures belong to the orientation it was made in) or is a model per label",
            d422="invalid orientation fields",
            d503="the queue is unreachable; nothing changed",
        ),
    },
)
def orient_job(job_id: str, body: OrientJobParams, who: OwnerDep, svc: ServicesDep, base: BaseUrlDep) -> JobOut:
    job = _job(svc, job_id, who)
    if job.state != "succeeded":
        raise Problem(409, f"job {job_id} has not succeeded ({job.state}); only a finished model can be re-oriented")
    if any(o.get("name") == "labels.zip" for o in job.outputs or []):
        raise Problem(409, f"job {job_id} is a model per label, placed by its label map: it is not re-oriented")
    report = svc.storage.read_output(job_id, "report.json", version_of(job))
    frame = json.loads(report).get("frame") or {} if report is not None else {}
    if str(frame.get("placed_by", "")).startswith("DICOM"):
        raise Problem(
            409, f"job {job_id} is a DICOM series: its headers place it in the patient; it cannot be re-oriented"
        )
    if (job.params or {}).get("defect") is not None:
        raise Problem(409, DEFECT_REORIENT.format(job=f"job {job_id}"))
    stale_before = utcnow() - dt.timedelta(seconds=svc.settings.stale_seconds)
    if not svc.db.start_orient(job_id, stale_before):
        raise Problem(409, f"job {job_id} is being re-oriented already; wait for it to finish")
    try:
        svc.queue.enqueue_orient(job_id, body.model_dump())
    except Exception as exc:
        svc.db.finish_orient(job_id)
        raise Problem(
            503,
            f"the queue is unreachable ({type(exc).__name__}); try again",
            code="queue_unavailable",
            headers={"Retry-After": str(RETRY_AFTER_SECONDS)},
        ) from None
    return svc.job_out(_job(svc, job_id, who), base)


@webhooks_router.get(
    "/webhook-secret",
    response_model=WebhookSecret,
    summary="the secret your jobs' webhooks are signed with (Standard Webhooks, HMAC-SHA256)",
    responses=KEYED,
)
def webhook_secret(who: OwnerDep, svc: ServicesDep) -> WebhookSecret:
    return WebhookSecret(secret=key_secret(svc.key, who))


@callbacks.post(
    "job-finished",
    operation_id="jobFinished",
    summary="the service POSTs the job to its callback_url when it ends (succeeded, failed or cancelled)",
    description="Sent to the `callback_url` given with `POST /v1/jobs` or `POST /v1/uploads`, once the job is "
    "succeeded, failed or cancelled: the job resource, as `GET /v1/jobs/{id}` answers it, signed as Standard "
    "Webhooks signs (HMAC-SHA256 with the key's secret, `GET /v1/webhook-secret`: `webhook-signature` is "
    '`v1,` + base64 of the HMAC of "{webhook-id}.{webhook-timestamp}.{body}"). Any 2xx answer is a delivery; '
    "anything else (or no answer within BONEMESH_WEBHOOK_TIMEOUT_SECONDS) is retried with exponential backoff for "
    "BONEMESH_WEBHOOK_RETRY_SECONDS (6 h); redirects are not followed. Every retry carries the same `webhook-id`: "
    "drop duplicates by it. Each attempt is recorded on the job (`webhook.attempts`).",
    status_code=200,
)
def job_finished(
    body: JobOut,
    webhook_id: Annotated[str, Header(alias="webhook-id", description="msg_<job id>_<state>: the same on every retry")],
    webhook_timestamp: Annotated[
        str, Header(alias="webhook-timestamp", description="Unix seconds when this attempt was signed")
    ],
    webhook_signature: Annotated[
        str, Header(alias="webhook-signature", description="v1,<base64 HMAC-SHA256>: verify it with your secret")
    ],
) -> None:
    """Never called on this service: it documents the request the service sends to a job's callback_url."""
