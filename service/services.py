"""What the routes and the background threads use, built once from the settings: the job records, the storage,
the broker client, the link-signing key and the upload thread pool (held on ``app.state.services``)."""

from __future__ import annotations

import datetime as dt
import time
from typing import Any

import anyio

from core.db import Database, Job
from core.logsafe import safe_logger
from core.queue import Queue
from core.settings import Settings
from core.storage import Storage, storage_from_settings, version_of
from engine.export.files import FILES
from engine.io.predecode_proc import DecoderChildren
from service import tokens
from service.pacs import api as pacs_api
from service.schemas import AttemptOut, JobError, JobOut, OutputFile, WebhookAttempt, WebhookOut

log = safe_logger("bonemesh.api")
UPLOAD_THREADS = 4  # threads for the blocking parts of all uploads together


class Services:
    """The service's collaborators.

    Args:
        settings: the process's settings.
    """

    def __init__(self, settings: Settings) -> None:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.db = Database(settings.db_url)
        self.storage: Storage = storage_from_settings(settings)
        if settings.download_links == "store" and not self.storage.presigns:
            raise ValueError("BONEMESH_DOWNLOAD_LINKS=store needs S3 storage (BONEMESH_STORAGE_URL=s3://...)")
        self.queue = Queue(settings.redis_url, settings.queue)
        self.key = settings.signing_key()
        self.upload_threads = anyio.CapacityLimiter(UPLOAD_THREADS)
        self.active_uploads = anyio.Semaphore(settings.active_uploads)
        # children decoding uploads' slices as they arrive (service.intake.start_decoder), one started ahead
        self.decoders: DecoderChildren | None = None
        if settings.decode_during_upload and settings.predecode_process:
            self.decoders = DecoderChildren(settings.predecode_wait_seconds)

    def close(self) -> None:
        """End what the services started (the decoding child waiting for an upload)."""
        if self.decoders is not None:
            self.decoders.close()

    async def in_upload_thread(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` in one of the uploads' threads."""
        return await anyio.to_thread.run_sync(fn, *args, limiter=self.upload_threads)

    def enqueue(self, job_id: str) -> bool:
        """Send the job's message; False (and the job stays queued, re-sent by the reconciler) when the broker is
        down."""
        try:
            self.queue.enqueue(job_id)
        except Exception as exc:  # broker down: the reconciler sends it later
            log.warning("could not enqueue job %s (%s); it stays queued and is re-sent later", job_id, exc)
            return False
        self.db.mark_enqueued(job_id)
        return True

    def accept(
        self,
        job_id: str,
        who: str,
        record: dict[str, Any],
        engine: dict[str, Any],
        name: str,
        size: int,
        callback_url: str | None = None,
        base_url: str = "",
    ) -> Job:
        """Record an uploaded job and send its message (blocking: call from a thread)."""
        job = self.db.create(
            who, record, name, size, job_id=job_id, engine_params=engine, callback_url=callback_url, base_url=base_url
        )
        self.enqueue(job_id)
        return self.db.get(job_id) or job

    def discard(self, writer: Any, job_id: str) -> None:
        """Drop a refused upload: the partial file and the job's folder (never raises)."""
        try:
            writer.abort()
        finally:
            self.storage.delete_job(job_id)

    def link(self, job: Job, name: str, base_url: str) -> tuple[str, int]:
        """A download link of an output and its expiry (Unix time): the API's signed link, or the store's
        presigned URL (``BONEMESH_DOWNLOAD_LINKS=store``), both valid for ``url_ttl_seconds``."""
        ttl = self.settings.url_ttl_seconds
        if self.settings.download_links == "store":
            expires = int(time.time()) + ttl
            url = self.storage.output_url(job.id, name, version_of(job), ttl)
            if url is not None:
                return url, expires
        token, expires = tokens.sign(self.key, job.id, name, ttl)
        return f"{base_url.rstrip('/')}/v1/files/{token}", expires

    def job_out(self, job: Job, base_url: str) -> JobOut:
        """The job resource as clients see it, with fresh signed links to its outputs."""
        outputs = None
        if job.state == "succeeded" and job.outputs:
            outputs = []
            for o in job.outputs:
                url, expires = self.link(job, o["name"], base_url)
                entry = FILES.get(o["name"])
                outputs.append(
                    OutputFile(
                        **o,
                        purpose=entry.purpose if entry is not None else "",
                        url=url,
                        expires_at=dt.datetime.fromtimestamp(expires, dt.UTC),
                    )
                )
        error = JobError(code=job.error_code, message=job.error_message or "") if job.error_code else None
        webhook = None
        if job.callback_url:
            webhook = WebhookOut(
                url=job.callback_url,
                state=job.webhook_state or "pending",  # type: ignore[arg-type]
                attempts=[WebhookAttempt(**a) for a in job.webhook_attempts or []],
            )
        return JobOut(
            id=job.id,
            state=job.state,  # type: ignore[arg-type]
            stage=job.stage,
            progress=round(job.progress, 1),
            upload_name=job.upload_name,
            upload_bytes=job.upload_bytes,
            params=job.params,
            attempts=job.attempts,
            runs=[runs_out(a) for a in getattr(job, "runs", None) or []],
            created_at=utc(job.created_at),
            started_at=utc(job.started_at),
            finished_at=utc(job.finished_at),
            error=error,
            outputs=outputs,
            webhook=webhook,
            **pacs_api.job_view(self.db, job),  # PACS jobs: source and delivery
        )


def runs_out(attempt: Any) -> AttemptOut:
    """An attempt's row (``core.db.Attempt``) as clients see it."""
    return AttemptOut(
        number=attempt.number,
        worker=attempt.worker,
        host=attempt.host,
        started_at=utc(attempt.started_at),  # type: ignore[arg-type]
        finished_at=utc(attempt.finished_at),
        outcome=attempt.outcome,
    )


def utc(value: dt.datetime | None) -> dt.datetime | None:
    """A stored naive UTC time as an aware one."""
    return None if value is None else value.replace(tzinfo=dt.UTC)
