"""Downloads through signed links (no API key): ``GET`` and ``HEAD``, with an ``ETag`` (``If-None-Match`` answers
304) and ``Cache-Control: private, max-age`` up to the link's expiry. The file is the output version the job's
record committed (``core.storage``): served from local disk, or streamed from an S3 store."""

from __future__ import annotations

import hashlib
import time
from email.utils import formatdate
from typing import Annotated

from fastapi import APIRouter, Header
from fastapi.responses import FileResponse, Response, StreamingResponse
from starlette.concurrency import iterate_in_threadpool

from core.storage import version_of
from engine.export.files import FILES
from service import tokens
from service.deps import ServicesDep
from service.headers import DOWNLOAD
from service.problems import Problem
from service.problems import problems as errors
from service.schemas import DOWNLOAD_CONTENT

router = APIRouter(prefix="/v1", tags=["files"])
RESPONSES = {
    200: {**DOWNLOAD_CONTENT, "headers": DOWNLOAD},
    304: {"description": "not modified: the ETag sent in If-None-Match is the file's", "headers": DOWNLOAD},
    **errors(403, 404, d403="the link does not verify (forged, malformed or expired)", d404="file gone"),
}


def _answer(svc: ServicesDep, token: str, if_none_match: str | None, head: bool = False) -> Response:
    try:
        job_id, name = tokens.verify(svc.key, token)
        expires = tokens.expiry(token)
    except tokens.BadToken as exc:
        raise Problem(403, str(exc)) from None
    job = svc.db.get(job_id)
    stored = None
    if job is not None and job.state == "succeeded":
        stored = svc.storage.output(job_id, name, version_of(job))  # the version the job's record committed
    if stored is None:
        raise Problem(404, "this file no longer exists (the job was deleted)")
    etag = '"' + hashlib.sha256(f"{job_id}/{name}/{stored.tag}/{stored.size}".encode()).hexdigest()[:32] + '"'
    headers = {
        "etag": etag,
        "cache-control": f"private, max-age={max(0, expires - int(time.time()))}",
        "expires": formatdate(expires, usegmt=True),
    }
    if if_none_match is not None and (
        if_none_match.strip() == "*" or etag in {t.strip().removeprefix("W/") for t in if_none_match.split(",")}
    ):
        return Response(status_code=304, headers=headers)
    media = FILES[name].media_type if name in FILES else "application/octet-stream"
    if stored.path is not None:  # local disk: served from the file (ranges, sendfile)
        return FileResponse(
            stored.path,
            media_type=media,
            filename=name,
            content_disposition_type="attachment",
            headers=headers,
            stat_result=stored.path.stat(),
        )
    headers |= {"content-length": str(stored.size), "content-disposition": f'attachment; filename="{name}"'}
    if head:
        return Response(status_code=200, media_type=media, headers=headers)
    chunks = svc.storage.open_output(job_id, name, version_of(job))  # streamed from the store, never whole
    return StreamingResponse(iterate_in_threadpool(chunks), media_type=media, headers=headers)


@router.get(
    "/files/{token:path}",
    summary="download an output through its signed link (no API key)",
    response_class=FileResponse,
    responses=RESPONSES,
)
def download(
    token: str,
    svc: ServicesDep,
    if_none_match: Annotated[str | None, Header(description="an ETag seen before: 304 if unchanged")] = None,
) -> Response:
    return _answer(svc, token, if_none_match)


@router.head(
    "/files/{token:path}",
    summary="the headers of a download (size, type, ETag, Cache-Control) without its body",
    response_class=FileResponse,
    responses=RESPONSES,
)
def download_head(
    token: str,
    svc: ServicesDep,
    if_none_match: Annotated[str | None, Header(description="an ETag seen before: 304 if unchanged")] = None,
) -> Response:
    return _answer(svc, token, if_none_match, head=True)
