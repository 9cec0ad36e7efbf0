"""Direct uploads (S3 storage only; routes in ``service.routes.direct``): the client declares the scan (name, size,
job params, callback) and gets presigned links for the parts of one multipart upload of the job's upload key; it
PUTs the parts straight to the store, then asks the API to complete. The API checks what the store holds (every
part there, exactly the declared size, within the limit), joins the parts, inspects the archive as it inspects an
upload through the API (``service.upload_check``, on a scratch copy read from the store), then records and queues
the job. The API never carries the scan's bytes.

A direct upload not completed within ``upload_ttl_seconds`` is aborted by the API's background sweep (``sweep``),
which also aborts multipart uploads of job uploads that no record explains (an API process killed between
starting one and recording it). A refused upload keeps nothing; one whose parts are missing or short stays open, so
the client can send them again and retry.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass
from typing import Any

from sqlalchemy import delete, select, update

from core.db import Database, Job, PendingUpload, utcnow
from core.logsafe import escape_control, safe_logger
from core.params import JobParams
from core.storage import DirectUploads, StoredPart
from service.intake import _inspect as inspect_stored
from service.problems import Problem
from service.services import Services
from service.uploads import UploadError
from service.webhooks import CallbackRefused, check_callback_url

log = safe_logger("bonemesh.api")
MIN_PART_BYTES = 8 << 20  # S3 wants 5 MiB or more for every part but the last; 8 MiB as the API's own uploads
MAX_PARTS = 10_000  # S3's limit on the parts of one upload
PARALLEL_PARTS = 4  # how many parts the page sends at once
NOT_S3 = (
    "direct uploads need S3 storage (BONEMESH_STORAGE_URL=s3://...); this service keeps files on its own disk: "
    "upload the scan with POST /v1/jobs"
)


def part_bytes_for(size: int) -> int:
    """The part size for a scan of ``size`` bytes: 8 MiB, or more (whole MiB) to stay within 10,000 parts."""
    needed = math.ceil(size / MAX_PARTS)
    return max(MIN_PART_BYTES, math.ceil(needed / (1 << 20)) << 20)


@dataclass(frozen=True)
class Begun:
    """A direct upload just begun: its record, and where each part goes."""

    record: PendingUpload
    links: list[Any]


def direct_of(svc: Services) -> DirectUploads:
    """The storage's direct uploads; 409 on local disk."""
    if svc.storage.direct is None:
        raise Problem(409, NOT_S3)
    return svc.storage.direct


def begin(
    svc: Services, who: str, filename: str, size: int, params: JobParams, callback: str | None, base_url: str
) -> Begun:
    """Validate the declared scan and start its multipart upload (blocking: call from a thread)."""
    direct = direct_of(svc)
    limit = svc.settings.max_upload_bytes
    if size > limit:
        raise Problem(413, f"the upload ({size:,} bytes) is over the limit of {limit:,} bytes")
    try:
        engine = params.engine_params()
    except ValueError as exc:
        raise Problem(422, f"params: {exc}", errors=[{"field": "params", "message": str(exc)}]) from None
    if callback is not None:
        try:
            check_callback_url(callback, svc.settings.webhook_allow_private)
        except CallbackRefused as exc:
            raise Problem(
                422, str(exc), code="callback_refused", errors=[{"field": "callback_url", "message": str(exc)}]
            ) from None
    job_id = Database.new_id()
    part = part_bytes_for(size)
    ttl = svc.settings.upload_ttl_seconds
    upload_id = direct.begin(job_id)
    record = PendingUpload(
        id=job_id,
        owner=who,
        store_upload_id=upload_id,
        state="open",
        upload_name=escape_control(filename)[-255:],
        upload_bytes=size,
        part_bytes=part,
        params=params.record(),
        engine_params=engine,
        callback_url=callback,
        base_url=base_url,
        created_at=utcnow(),
        expires_at=utcnow() + dt.timedelta(seconds=ttl),
    )
    try:
        with svc.db.session() as s:
            s.add(record)
        links = direct.part_links(job_id, upload_id, max(1, math.ceil(size / part)), ttl)
    except BaseException:
        direct.abort(job_id, upload_id)
        forget(svc.db, job_id)
        raise
    log.info("job %s: direct upload of %d bytes begun", job_id, size)
    return Begun(record, links)


def again(svc: Services, upload_id: str, who: str) -> Begun:
    """The direct upload ``upload_id`` as begun, with fresh part links (its ``POST /v1/uploads`` sent again with its
    Idempotency-Key); 404 once it is completed, aborted or expired."""
    direct = direct_of(svc)
    row = pending_of(svc.db, upload_id, who)
    ttl = max(1, int((row.expires_at - utcnow()).total_seconds()))
    count = max(1, math.ceil(row.upload_bytes / row.part_bytes))
    return Begun(row, direct.part_links(row.id, row.store_upload_id, count, ttl))


def forget(db: Database, upload_id: str) -> None:
    """Remove a pending upload's record."""
    with db.session() as s:
        s.execute(delete(PendingUpload).where(PendingUpload.id == upload_id))


def pending_of(db: Database, upload_id: str, who: str) -> PendingUpload:
    """The caller's pending upload; 404 when there is none (never begun, completed, aborted, expired or another
    key's)."""
    with db.session() as s:
        row = s.get(PendingUpload, upload_id)
    if row is None or row.owner != who or row.expires_at <= utcnow():
        raise Problem(404, f"no direct upload {upload_id} in progress for this API key (completed, aborted or expired)")
    return row


def _take(db: Database, row: PendingUpload) -> None:
    """Mark the upload as being completed (one completion at a time); 409 when another is under way."""
    with db.session() as s:
        res = s.execute(
            update(PendingUpload)
            .where(PendingUpload.id == row.id, PendingUpload.state == "open")
            .values(state="completing")
        )
    if res.rowcount != 1:
        raise Problem(409, f"direct upload {row.id} is being completed already")


def _reopen(db: Database, upload_id: str) -> None:
    with db.session() as s:
        s.execute(update(PendingUpload).where(PendingUpload.id == upload_id).values(state="open"))


def _check_parts(row: PendingUpload, stored: list[StoredPart], sent: list[tuple[int, str]] | None) -> None:
    """What the store holds is the declared scan: parts 1..n, their sizes adding up to the declared size (422, the
    upload stays open for the missing bytes); the client's ETags, when sent, are those of the stored parts."""
    numbers = [p.number for p in stored]
    want = max(1, math.ceil(row.upload_bytes / row.part_bytes))
    missing = sorted(set(range(1, want + 1)) - set(numbers))
    got = sum(p.size for p in stored)
    if missing or got != row.upload_bytes or numbers != list(range(1, len(numbers) + 1)):
        shown = ", ".join(map(str, missing[:10])) + (", ..." if len(missing) > 10 else "")
        why = f"parts {shown} not received" if missing else f"{got:,} bytes received, {row.upload_bytes:,} declared"
        raise Problem(
            422, f"the upload is not complete: {why}; send the parts again, then complete it", code="upload_incomplete"
        )
    if sent is not None:
        etags = {p.number: p.etag.strip('"') for p in stored}
        wrong = [n for n, tag in sent if etags.get(n) != tag.strip().removeprefix("W/").strip('"')]
        if wrong or {n for n, _ in sent} != set(numbers):
            raise Problem(
                422,
                "the parts' ETags do not match what the store holds (send every part's ETag, or none)",
                code="upload_incomplete",
            )


def completed(svc: Services, upload_id: str, who: str) -> Job | None:
    """The job an upload of the caller's was completed into (its id is the upload's), else None: a completion sent
    again (its answer lost on a flaky network) is answered with that job, and no second one is made."""
    with svc.db.session() as s:
        pending = s.get(PendingUpload, upload_id)
    return svc.db.get(upload_id, who) if pending is None else None


def complete(svc: Services, upload_id: str, who: str, sent: list[tuple[int, str]] | None) -> Job:
    """Join the parts, check the archive, record and queue the job (blocking: call from a thread)."""
    direct = direct_of(svc)
    row = pending_of(svc.db, upload_id, who)
    _take(svc.db, row)
    try:
        stored = direct.parts(row.id, row.store_upload_id)
        _check_parts(row, stored, sent)
        direct.complete(row.id, row.store_upload_id, [(p.number, p.etag) for p in stored])
    except FileNotFoundError:
        forget(svc.db, row.id)
        raise Problem(404, f"direct upload {upload_id} is gone from the store (aborted or expired)") from None
    except ValueError as exc:
        _reopen(svc.db, row.id)
        raise Problem(422, str(exc)) from None
    except BaseException:
        _reopen(svc.db, row.id)
        raise
    try:
        params = JobParams.model_validate(row.params)
        summary = inspect_stored(svc.storage, row.id, row.upload_name, params)
        log.info("job %s: direct upload of %d bytes: %s", row.id, row.upload_bytes, summary)
        job = svc.accept(
            row.id,
            who,
            row.params,
            row.engine_params,
            row.upload_name or "upload",
            row.upload_bytes,
            row.callback_url,
            row.base_url or "",
        )
    except BaseException as exc:
        svc.storage.delete_job(row.id)
        forget(svc.db, row.id)
        if isinstance(exc, UploadError):
            raise Problem(exc.status, exc.detail) from None
        raise
    forget(svc.db, row.id)
    return job


def abort(svc: Services, upload_id: str, who: str) -> None:
    """Drop a pending upload and what the store holds of it."""
    direct = direct_of(svc)
    row = pending_of(svc.db, upload_id, who)
    _take(svc.db, row)
    direct.abort(row.id, row.store_upload_id)
    svc.storage.delete_job(row.id)
    forget(svc.db, row.id)


def sweep(svc: Services) -> dict[str, int]:
    """Abort direct uploads past their time (``upload_ttl_seconds``), and multipart uploads of job uploads begun
    before that which no pending record or job explains."""
    direct = svc.storage.direct
    if direct is None:
        return {"expired": 0, "orphans": 0}
    now = utcnow()
    with svc.db.session() as s:
        expired = list(s.scalars(select(PendingUpload).where(PendingUpload.expires_at <= now)).all())
    for row in expired:
        if svc.db.get(row.id) is None:  # completed into a job just before the API stopped: keep its upload
            direct.abort(row.id, row.store_upload_id)
            svc.storage.delete_job(row.id)
        forget(svc.db, row.id)
        log.info("job %s: direct upload not completed in time; aborted", row.id)
    cutoff = (now - dt.timedelta(seconds=svc.settings.upload_ttl_seconds)).replace(tzinfo=dt.UTC)
    orphans = 0
    for job_id, store_id in direct.pending(cutoff):
        with svc.db.session() as s:
            known = s.get(PendingUpload, job_id) is not None or s.get(Job, job_id) is not None
        if not known:
            direct.abort(job_id, store_id)
            orphans += 1
            log.info("job %s: a multipart upload no record explains; aborted", job_id)
    return {"expired": len(expired), "orphans": orphans}
