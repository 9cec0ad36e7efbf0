"""Direct uploads: the client sends the scan straight to the S3 store through presigned part links, then the API
completes the upload and creates the job (``service.direct``). With local storage these routes answer 409 and
``GET /v1/upload-options`` says so: the upload goes through ``POST /v1/jobs``."""

from __future__ import annotations

import datetime as dt

from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from service import direct, idempotency
from service import headers as hdr
from service.deps import BaseUrlDep, OwnerDep, ServicesDep
from service.idempotency import KeyHeader
from service.problems import problems as errors
from service.routes.jobs import KEYED
from service.schemas import (
    DirectUploadComplete,
    DirectUploadCreate,
    DirectUploadOut,
    JobOut,
    UploadOptions,
    UploadPart,
)

router = APIRouter(prefix="/v1", tags=["uploads"])
NO_DIRECT = "storage is the service's own disk (no direct uploads): use POST /v1/jobs"


@router.get(
    "/upload-options",
    response_model=UploadOptions,
    summary="how to upload: straight to the store (direct, S3 storage) or through POST /v1/jobs",
    responses=KEYED,
)
def upload_options(who: OwnerDep, svc: ServicesDep) -> UploadOptions:
    on = svc.storage.direct is not None
    return UploadOptions(
        direct=on,
        reason=None if on else direct.NOT_S3,
        max_upload_bytes=svc.settings.max_upload_bytes,
        parallel_parts=direct.PARALLEL_PARTS,
    )


@router.post(
    "/uploads",
    status_code=201,
    response_model=DirectUploadOut,
    summary="begin a direct upload: links to PUT the scan's parts straight to the store (S3 storage only)",
    responses={
        201: {"description": "the upload begun (or the one its Idempotency-Key began)", "headers": hdr.CREATED},
        **KEYED,
        **errors(
            400,
            404,
            409,
            413,
            422,
            d400="the body is not valid JSON",
            d404="the Idempotency-Key's upload is completed, aborted or expired",
            d409=f"{NO_DIRECT}; or a request with this Idempotency-Key is still being carried out",
            d413="the declared size is over the limit",
            d422="invalid params or callback_url, or an Idempotency-Key used with another request",
        ),
    },
)
async def begin_upload(
    body: DirectUploadCreate, who: OwnerDep, svc: ServicesDep, base: BaseUrlDep, idempotency_key: KeyHeader = None
) -> Response:
    args = (svc, who, body.filename, body.size, body.params, body.callback_url, base)
    if idempotency_key is None:
        return _begun(await svc.in_upload_thread(direct.begin, *args))
    fingerprint = idempotency.canonical({"kind": "direct", **body.model_dump(mode="json")})
    found = await svc.in_upload_thread(idempotency.reserve, svc, who, idempotency.UPLOADS, idempotency_key)
    if isinstance(found, idempotency.Hold):
        begun = await idempotency.held(found, svc.in_upload_thread(direct.begin, *args))
        await svc.in_upload_thread(found.finish, fingerprint, begun.record.id, 201)
        return _begun(begun)
    upload_id = idempotency.replayed(found, fingerprint)
    return _begun(await svc.in_upload_thread(direct.again, svc, upload_id, who), replayed=True)


def _begun(begun: direct.Begun, *, replayed: bool = False) -> Response:
    row, part = begun.record, begun.record.part_bytes
    parts = [
        UploadPart(
            number=link.number,
            offset=(link.number - 1) * part,
            bytes=min(part, row.upload_bytes - (link.number - 1) * part),
            url=link.url,
            headers=link.headers,
        )
        for link in begun.links
    ]
    out = DirectUploadOut(
        id=row.id,
        part_bytes=part,
        parts=parts,
        expires_at=row.expires_at.replace(tzinfo=dt.UTC),
        complete_url=f"/v1/uploads/{row.id}/complete",
        abort_url=f"/v1/uploads/{row.id}",
    )
    headers = {"Location": f"/v1/uploads/{row.id}"}
    if replayed:
        headers[idempotency.REPLAYED] = "true"
    return JSONResponse(out.model_dump(mode="json"), status_code=201, headers=headers)


@router.post(
    "/uploads/{upload_id}/complete",
    status_code=202,
    response_model=JobOut,
    summary="complete a direct upload: the parts are joined, the archive checked, and the job created and queued",
    responses={
        202: {
            "description": "the job, queued; for an upload completed already, the job it became (Idempotent-Replayed)",
            "headers": hdr.CREATED,
        },
        **KEYED,
        **errors(
            400,
            404,
            409,
            413,
            415,
            422,
            d400="the body is not valid JSON",
            d404="no such upload in progress for this key (never begun, aborted or expired)",
            d409=f"being completed already; or {NO_DIRECT}",
            d413="the upload is larger than the limit",
            d415="not an archive bonemesh reads",
            d422="parts missing or of the wrong size (the upload stays open), or an archive that cannot be a scan",
        ),
    },
)
async def complete_upload(
    upload_id: str, body: DirectUploadComplete, who: OwnerDep, svc: ServicesDep, base: BaseUrlDep
) -> Response:
    sent = None if body.parts is None else [(p.number, p.etag) for p in body.parts]
    headers = {}
    if (job := await run_in_threadpool(direct.completed, svc, upload_id, who)) is not None:
        headers[idempotency.REPLAYED] = "true"  # completed already: its job, not a second one
    else:
        async with svc.active_uploads:  # the archive check reads the scan from the store: as many at once as uploads
            job = await svc.in_upload_thread(direct.complete, svc, upload_id, who, sent)
    out = svc.job_out(job, base).model_dump(mode="json")
    return JSONResponse(out, status_code=202, headers={"Location": f"/v1/jobs/{job.id}", **headers})


@router.delete(
    "/uploads/{upload_id}",
    status_code=204,
    summary="abort a direct upload: the store drops every part received",
    responses={**KEYED, **errors(404, 409, d404="no such upload in progress for this key", d409=NO_DIRECT)},
)
async def abort_upload(upload_id: str, who: OwnerDep, svc: ServicesDep) -> Response:
    await run_in_threadpool(direct.abort, svc, upload_id, who)
    return Response(status_code=204)
