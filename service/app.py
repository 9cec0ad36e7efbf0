"""The bonemesh REST API (FastAPI): upload a scan, follow the job, download the models through signed links.

The API records jobs in the database, streams uploads to storage, and enqueues by task name; it never imports
Warp or the worker. A background reconciler re-enqueues jobs whose broker message is gone (Redis restarted) and
jobs whose worker stopped sending heartbeats (worker killed): the job records are the truth.

Blocking work (file writes, fsync, inspecting the archive, database writes, the broker) runs in threads, and an
upload's threads come from a small pool of their own: a burst of uploads never queues the status reads, which
run in the default pool. Every error is a problem+json document (:mod:`service.problems`).
"""

import contextlib
import datetime as dt
import hmac
import json
import threading
from collections.abc import AsyncIterator
from typing import Annotated, Any

import anyio
from fastapi import Depends, FastAPI, Header, Query, Request
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi_offline import FastAPIOffline
from pydantic import ValidationError

from service import problems, tokens
from service.db import Database, Job, owner_of, utcnow
from service.logsafe import safe_logger
from service.pacs import api as pacs_api
from service.params import JobParams
from service.problems import Problem
from service.problems import problems as errors
from service.queue import Queue
from service.schemas import (
    DOWNLOAD_CONTENT,
    UPLOAD_BODY,
    JobError,
    JobList,
    JobOut,
    OutputFile,
    Readiness,
    add_job_params,
)
from service.settings import Settings, get_settings
from service.storage import OUTPUTS, Storage, UploadTooLarge, is_storage_full, storage_from_settings
from service.upload_check import inspect_upload
from service.uploads import UploadError, read_multipart

log = safe_logger("bonemesh.api")
MULTIPART_SLACK = 1 << 20  # multipart headers and boundaries around the file
UPLOAD_THREADS = 4  # threads for the blocking parts of all uploads together
MAX_OFFSET = 2**31 - 1
FULL = "the data volume is full: the upload was not kept; try again later or ask the operator to free space"


class Services:
    """What the routes use, built from the settings."""

    def __init__(self, settings: Settings) -> None:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.db = Database(settings.db_url)
        self.storage: Storage = storage_from_settings(settings.data_dir)
        self.queue = Queue(settings.redis_url, settings.queue)
        self.key = settings.signing_key()
        self.upload_threads = anyio.CapacityLimiter(UPLOAD_THREADS)
        self.active_uploads = anyio.Semaphore(settings.active_uploads)
        self._stop = threading.Event()

    async def in_upload_thread(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` in one of the uploads' threads."""
        return await anyio.to_thread.run_sync(fn, *args, limiter=self.upload_threads)

    def enqueue(self, job_id: str) -> bool:
        try:
            self.queue.enqueue(job_id)
        except Exception as exc:  # broker down: the reconciler sends it later
            log.warning("could not enqueue job %s (%s); it stays queued and is re-sent later", job_id, exc)
            return False
        self.db.mark_enqueued(job_id)
        return True

    def reconcile(self) -> dict[str, int]:
        """Re-enqueue lost jobs: running with a stale heartbeat, or queued without a message in the broker."""
        s = self.settings
        now = utcnow()
        queued, stale = self.db.lost_jobs(
            queued_before=now - dt.timedelta(seconds=s.reconcile_seconds),
            stale_before=now - dt.timedelta(seconds=s.stale_seconds),
        )
        requeued = 0
        for job_id in stale:
            if self.db.requeue_stale(job_id, now - dt.timedelta(seconds=s.stale_seconds)):
                log.warning("job %s: its worker stopped (no heartbeat for %gs); re-queued", job_id, s.stale_seconds)
                requeued += self.enqueue(job_id)
        resent = 0
        if queued:
            present = self.queue.jobs_in_broker()
            for job_id in queued:
                if job_id not in present:
                    log.warning("job %s: queued but its message is not in the broker; re-sent", job_id)
                    resent += self.enqueue(job_id)
        return {"requeued_stale": requeued, "resent": resent}

    def run_reconciler(self) -> None:
        while not self._stop.wait(self.settings.reconcile_seconds):
            try:
                self.reconcile()
            except Exception as exc:  # Redis or the database down for a moment: try again next round
                log.warning("reconciler: %s", exc)

    def accept(self, job_id: str, who: str, params: dict[str, Any], name: str, size: int) -> Job:
        """Record an uploaded job and send its message (blocking: call from a thread)."""
        job = self.db.create(who, params, name, size, job_id=job_id)
        self.enqueue(job_id)
        return self.db.get(job_id) or job

    def discard(self, writer: Any, job_id: str) -> None:
        """Drop a refused upload: the partial file and the job's folder (never raises)."""
        try:
            writer.abort()
        finally:
            self.storage.delete_job(job_id)

    def job_out(self, job: Job, base_url: str) -> JobOut:
        outputs = None
        if job.state == "succeeded" and job.outputs:
            outputs = []
            for o in job.outputs:
                token, expires = tokens.sign(self.key, job.id, o["name"], self.settings.url_ttl_seconds)
                outputs.append(
                    OutputFile(
                        **o,
                        url=f"{base_url.rstrip('/')}/v1/files/{token}",
                        expires_at=dt.datetime.fromtimestamp(expires, dt.UTC),
                    )
                )
        error = JobError(code=job.error_code, message=job.error_message or "") if job.error_code else None
        return JobOut(
            id=job.id,
            state=job.state,  # type: ignore[arg-type]
            stage=job.stage,
            progress=round(job.progress, 1),
            upload_name=job.upload_name,
            upload_bytes=job.upload_bytes,
            params=job.params,
            attempts=job.attempts,
            created_at=_utc(job.created_at),
            started_at=_utc(job.started_at),
            finished_at=_utc(job.finished_at),
            error=error,
            outputs=outputs,
            **pacs_api.job_view(self.db, job),  # PACS jobs: source and delivery
        )


def _utc(value: dt.datetime | None) -> dt.datetime | None:
    return None if value is None else value.replace(tzinfo=dt.UTC)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API application (``uvicorn --factory service.app:create_app``)."""
    settings = settings or get_settings()
    holder: dict[str, Services] = {}

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        svc = Services(settings)
        holder["svc"] = svc
        app.state.data_dir = settings.data_dir
        thread = threading.Thread(target=svc.run_reconciler, name="reconciler", daemon=True)
        thread.start()
        yield
        svc._stop.set()

    app = FastAPIOffline(  # /docs and /redoc with their scripts served from the package: no CDN
        title="bonemesh",
        version="1.0",
        description="Bone surface models from CT and micro-CT scans: upload a slice archive or DICOM series, get "
        "a watertight STL in millimetres for printing and light GLB models (metres) for phones and AR.",
        lifespan=lifespan,
        static_url="/docs/static",
    )
    problems.install(app)

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            app.openapi_schema = add_job_params(problems.fix_openapi(schema))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

    def svc() -> Services:
        return holder["svc"]

    def owner(x_api_key: Annotated[str | None, Header(description="your API key")] = None) -> str:
        ok = False
        for key in settings.api_keys:  # every key compared, in constant time
            ok |= x_api_key is not None and hmac.compare_digest(x_api_key.encode(), key.encode())
        if not ok:
            raise Problem(401, "send a valid API key in the X-API-Key header")
        return owner_of(x_api_key or "")

    Owner = Annotated[str, Depends(owner)]
    keyed = errors(401, d401="missing or unknown API key")

    @app.get("/healthz", tags=["health"], summary="the process is up")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get(
        "/readyz",
        tags=["health"],
        summary="database, Redis and storage are reachable",
        response_model=Readiness,
        responses={503: {"model": Readiness, "description": "a dependency is unreachable (status 'not ready')"}},
    )
    def readyz() -> JSONResponse:
        checks: dict[str, str] = {}
        s = svc()
        for name, probe in (("database", s.db.ping), ("redis", s.queue.ping), ("storage", s.storage.ping)):
            try:
                probe()
                checks[name] = "ok"
            except Exception as exc:
                checks[name] = f"unreachable: {type(exc).__name__}: {exc}"
        ready = all(v == "ok" for v in checks.values())
        return JSONResponse({"status": "ready" if ready else "not ready", "checks": checks}, 200 if ready else 503)

    @app.post(
        "/v1/jobs",
        status_code=202,
        response_model=JobOut,
        tags=["jobs"],
        summary="upload a scan (multipart) or name a DICOMweb series (JSON), and start a reconstruction",
        responses={
            **keyed,
            **errors(
                400,
                413,
                415,
                422,
                507,
                d400="malformed or incomplete multipart body, or a part sent twice",
                d413="the upload is larger than the limit",
                d415="not multipart, or not an archive bonemesh reads",
                d422="invalid params, or an archive that cannot be a scan",
                d507="the data volume cannot hold the upload (nothing was kept)",
            ),
        },
        openapi_extra={"requestBody": UPLOAD_BODY},
    )
    async def create_job(request: Request, who: Owner) -> Response:
        s = svc()
        if pacs_api.is_json(request):  # a DICOMweb series instead of a file
            job = await pacs_api.create_source_job(request, s, who)
            body = s.job_out(job, _base(request, settings)).model_dump(mode="json")
            return JSONResponse(body, status_code=202, headers={"Location": f"/v1/jobs/{job.id}"})
        limit = settings.max_upload_bytes
        declared = request.headers.get("content-length")
        size = int(declared) if declared and declared.isdigit() and len(declared) < 20 else None
        if size is not None and size > limit + MULTIPART_SLACK:
            raise Problem(413, f"the upload ({size:,} bytes) is over the limit of {limit:,} bytes")
        free = s.storage.free_bytes()
        if size is not None and free is not None and size > free:
            raise Problem(507, f"{FULL} ({size:,} bytes sent, {free:,} free)")
        async with s.active_uploads:
            job = await _receive(request, s, who, limit)
        body = s.job_out(job, _base(request, settings)).model_dump(mode="json")
        return JSONResponse(body, status_code=202, headers={"Location": f"/v1/jobs/{job.id}"})

    async def _receive(request: Request, s: Services, who: str, limit: int) -> Job:
        """Stream, check and record one upload; nothing of a refused one is kept."""
        job_id = Database.new_id()
        writer = await s.in_upload_thread(s.storage.upload_writer, job_id, limit)
        try:
            parsed = await read_multipart(
                request.headers.get("content-type", ""),
                request.stream(),
                lambda data: s.in_upload_thread(writer.write, data),
            )
            params = _parse_params(parsed.fields.get("params"))
            await s.in_upload_thread(writer.commit)
            summary = await s.in_upload_thread(inspect_upload, s.storage.upload_path(job_id), parsed.filename, params)
            log.info("job %s: upload of %d bytes: %s", job_id, writer.size, summary)
            name = parsed.filename or "upload"
            return await s.in_upload_thread(  # type: ignore[no-any-return]
                s.accept, job_id, who, params.record(), name, writer.size
            )
        except Exception as exc:
            await s.in_upload_thread(s.discard, writer, job_id)
            if isinstance(exc, UploadTooLarge):
                raise Problem(413, str(exc)) from None
            if isinstance(exc, UploadError):
                raise Problem(exc.status, exc.detail) from None
            if is_storage_full(exc):
                log.error("job %s: upload refused, the data volume is full (%s)", job_id, exc)
                raise Problem(507, FULL) from None
            raise
        except BaseException:  # cancelled: clean up without awaiting
            s.discard(writer, job_id)
            raise

    @app.get("/v1/jobs", response_model=JobList, tags=["jobs"], summary="your jobs, newest first", responses=keyed)
    def list_jobs(
        request: Request,
        who: Owner,
        limit: Annotated[int, Query(ge=1, le=200)] = 50,
        offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
    ) -> JobList:
        s = svc()
        rows, total = s.db.list(who, limit, offset)
        base = _base(request, settings)
        return JobList(items=[s.job_out(j, base) for j in rows], total=total, limit=limit, offset=offset)

    def _job(job_id: str, who: str) -> Job:
        job = svc().db.get(job_id, who)
        if job is None:
            raise Problem(404, f"no job {job_id} for this API key")
        return job

    @app.get(
        "/v1/jobs/{job_id}", response_model=JobOut, tags=["jobs"], summary="a job", responses={**keyed, **errors(404)}
    )
    def get_job(job_id: str, request: Request, who: Owner) -> JobOut:
        return svc().job_out(_job(job_id, who), _base(request, settings))

    @app.post(
        "/v1/jobs/{job_id}/cancel",
        response_model=JobOut,
        tags=["jobs"],
        summary="cancel a queued or running job (the record stays, as cancelled; its files are removed)",
        responses={**keyed, **errors(404, 409, d409="the job has already finished")},
    )
    def cancel_job(job_id: str, request: Request, who: Owner) -> JobOut:
        s = svc()
        job = _job(job_id, who)
        if job.state != "cancelled":
            if not s.db.cancel(job_id):
                raise Problem(409, f"job {job_id} has already {job.state}; delete it to remove it and its files")
            s.storage.delete_job(job_id)
        return s.job_out(_job(job_id, who), _base(request, settings))

    @app.delete(
        "/v1/jobs/{job_id}",
        status_code=204,
        tags=["jobs"],
        summary="delete a job and its files (a running one is stopped); afterwards the job answers 404",
        responses={**keyed, **errors(404)},
    )
    def delete_job(job_id: str, who: Owner) -> Response:
        s = svc()
        _job(job_id, who)
        s.db.delete(job_id)
        s.storage.delete_job(job_id)
        return Response(status_code=204)

    @app.get(
        "/v1/files/{token:path}",
        tags=["files"],
        summary="download an output through its signed link (no API key)",
        response_class=FileResponse,
        responses={
            200: DOWNLOAD_CONTENT,
            **errors(403, 404, d403="the link does not verify (forged, malformed or expired)", d404="file gone"),
        },
    )
    def download(token: str) -> FileResponse:
        s = svc()
        try:
            job_id, name = tokens.verify(s.key, token)
        except tokens.BadToken as exc:
            raise Problem(403, str(exc)) from None
        job = s.db.get(job_id)
        path = s.storage.output_path(job_id, name) if job is not None and job.state == "succeeded" else None
        if path is None:
            raise Problem(404, "this file no longer exists (the job was deleted)")
        media = OUTPUTS.get(name, ("file", "application/octet-stream"))[1]
        return FileResponse(path, media_type=media, filename=name, content_disposition_type="attachment")

    return app


def _parse_params(text: str | None) -> JobParams:
    if text is None or not text.strip():
        return JobParams()
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as exc:
        reason = "it is nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise Problem(422, f"params is not valid JSON: {reason}") from None
    if not isinstance(data, dict):
        raise Problem(422, "params must be a JSON object")
    try:
        params = JobParams.model_validate(data)
    except (ValidationError, RecursionError) as exc:
        if isinstance(exc, RecursionError):
            raise Problem(422, "params is nested too deeply") from None
        errs = [
            {"field": ".".join(["params", *(str(p) for p in e["loc"])]).rstrip("."), "message": e["msg"]}
            for e in exc.errors()
        ]
        raise Problem(422, "; ".join(f"{e['field']}: {e['message']}" for e in errs), errors=errs) from None
    try:
        params.engine_params()
    except ValueError as exc:
        raise Problem(422, f"params: {exc}", errors=[{"field": "params", "message": str(exc)}]) from None
    return params


def _base(request: Request, settings: Settings) -> str:
    return settings.public_url or str(request.base_url)
