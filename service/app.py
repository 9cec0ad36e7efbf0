"""The bonemesh REST API (FastAPI): upload a scan, follow the job, download the models through signed links.

The API records jobs in the database, streams uploads to storage, and enqueues by task name; it never imports
Warp or the worker. A background reconciler re-enqueues jobs whose broker message is gone (Redis restarted) and
jobs whose worker stopped sending heartbeats (worker killed): the job records are the truth.
"""

import contextlib
import datetime as dt
import hmac
import json
import logging
import threading
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, Header, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, Field, ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from service import tokens
from service.db import Database, Job, owner_of, utcnow
from service.params import JobParams
from service.queue import Queue
from service.settings import Settings, get_settings
from service.storage import OUTPUTS, Storage, UploadTooLarge, storage_from_settings
from service.uploads import UploadError, read_multipart, relabel

log = logging.getLogger("bonemesh.api")
PROBLEM = "application/problem+json"
MULTIPART_SLACK = 1 << 20  # multipart headers and boundaries around the file


class Problem(Exception):
    """An error answered as application/problem+json."""

    def __init__(self, status: int, title: str, detail: str, **extra: Any) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail, self.extra = status, title, detail, extra


class ProblemBody(BaseModel):
    type: str = "about:blank"
    title: str
    status: int
    detail: str
    errors: list[dict[str, Any]] | None = None


class JobError(BaseModel):
    code: str = Field(description="machine-readable reason, e.g. bad_input, no_surface, time_limit, internal_error")
    message: str = Field(description="what went wrong, in words")


class OutputFile(BaseModel):
    name: str
    kind: str = Field(description="print (STL, mm), model (GLB, m), phone (Draco GLB), ar (GLB), report")
    media_type: str
    bytes: int
    triangles: int | None
    url: str = Field(description="signed download link; works without the API key until expires_at")
    expires_at: dt.datetime


class JobOut(BaseModel):
    id: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    stage: str | None
    progress: float = Field(ge=0, le=100)
    upload_name: str
    upload_bytes: int
    params: dict[str, Any]
    attempts: int
    created_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None
    error: JobError | None
    outputs: list[OutputFile] | None


class JobList(BaseModel):
    items: list[JobOut]
    total: int
    limit: int
    offset: int


class Services:
    """What the routes use, built from the settings."""

    def __init__(self, settings: Settings) -> None:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.db = Database(settings.db_url)
        self.storage: Storage = storage_from_settings(settings.data_dir)
        self.queue = Queue(settings.redis_url, settings.queue)
        self.key = settings.signing_key()
        self._stop = threading.Event()

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

    app = FastAPI(
        title="bonemesh",
        version="1.0",
        description="Bone surface models from CT and micro-CT scans: upload a slice archive or DICOM series, get "
        "a watertight STL in millimetres for printing and light GLB models (metres) for phones and AR.",
        lifespan=lifespan,
        responses={401: {"model": ProblemBody, "description": "missing or unknown API key"}},
    )

    def svc() -> Services:
        return holder["svc"]

    def owner(x_api_key: Annotated[str | None, Header(description="your API key")] = None) -> str:
        ok = False
        for key in settings.api_keys:  # every key compared, in constant time
            ok |= x_api_key is not None and hmac.compare_digest(x_api_key.encode(), key.encode())
        if not ok:
            raise Problem(401, "Unauthorized", "send a valid API key in the X-API-Key header")
        return owner_of(x_api_key or "")

    @app.exception_handler(Problem)
    async def _problem(_: Request, exc: Problem) -> JSONResponse:
        body = {"type": "about:blank", "title": exc.title, "status": exc.status, "detail": exc.detail, **exc.extra}
        return JSONResponse(body, status_code=exc.status, media_type=PROBLEM)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = exc.status_code
        body = {"type": "about:blank", "title": _title(code), "status": code, "detail": exc.detail}
        return JSONResponse(body, status_code=exc.status_code, media_type=PROBLEM, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"field": ".".join(str(p) for p in e["loc"]), "message": e["msg"]} for e in exc.errors()]
        detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
        body = {"type": "about:blank", "title": "Unprocessable Content", "status": 422, "detail": detail}
        return JSONResponse({**body, "errors": errors}, status_code=422, media_type=PROBLEM)

    problems = {n: {"model": ProblemBody, "content": {PROBLEM: {}}} for n in (404,)}

    @app.get("/healthz", tags=["health"], summary="the process is up")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", tags=["health"], summary="database, Redis and storage are reachable")
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
        summary="upload a scan and start a reconstruction",
        responses={
            400: {"model": ProblemBody},
            413: {"model": ProblemBody, "description": "the upload is larger than the limit"},
            415: {"model": ProblemBody, "description": "not multipart, or not an archive bonemesh reads"},
            422: {"model": ProblemBody, "description": "invalid params, or an archive that cannot be a scan"},
        },
        openapi_extra={
            "requestBody": {
                "required": True,
                "content": {
                    "multipart/form-data": {
                        "schema": {
                            "type": "object",
                            "required": ["file"],
                            "properties": {
                                "file": {
                                    "type": "string",
                                    "format": "binary",
                                    "description": "zip, tar or tar.gz of 2-D slices, or a DICOM series as a zip",
                                },
                                "params": {
                                    "type": "string",
                                    "description": "JSON object of JobParams (iso or preset, spacing, reduction...)",
                                },
                            },
                        },
                        "encoding": {"params": {"contentType": "application/json"}},
                    }
                },
            }
        },
    )
    async def create_job(request: Request, who: Annotated[str, Depends(owner)]) -> Response:
        s = svc()
        limit = settings.max_upload_bytes
        declared = request.headers.get("content-length")
        if declared and declared.isdigit() and int(declared) > limit + MULTIPART_SLACK:
            detail = f"the upload ({int(declared):,} bytes) is over the limit of {limit:,} bytes"
            raise Problem(413, "Content Too Large", detail)
        job_id = Database.new_id()
        writer = s.storage.upload_writer(job_id, limit)
        try:
            parsed = await read_multipart(request.headers.get("content-type", ""), request.stream(), writer)
            params = _parse_params(parsed.fields.get("params"))
            writer.commit()
            await run_in_threadpool(_inspect, s.storage.upload_path(job_id), parsed.filename)
        except BaseException as exc:  # nothing of a refused upload is kept
            writer.abort()
            s.storage.delete_job(job_id)
            if isinstance(exc, UploadTooLarge):
                raise Problem(413, "Content Too Large", str(exc)) from None
            if isinstance(exc, UploadError):
                raise Problem(exc.status, _title(exc.status), exc.detail) from None
            raise
        name = parsed.filename or "upload"
        job = s.db.create(who, params.model_dump(exclude_none=True), name, writer.size, job_id=job_id)
        await run_in_threadpool(s.enqueue, job_id)
        job = s.db.get(job_id) or job
        body = s.job_out(job, _base(request, settings)).model_dump(mode="json")
        return JSONResponse(body, status_code=202, headers={"Location": f"/v1/jobs/{job_id}"})

    @app.get("/v1/jobs", response_model=JobList, tags=["jobs"], summary="your jobs, newest first")
    def list_jobs(
        request: Request,
        who: Annotated[str, Depends(owner)],
        limit: Annotated[int, Query(ge=1, le=200)] = 50,
        offset: Annotated[int, Query(ge=0)] = 0,
    ) -> JobList:
        s = svc()
        rows, total = s.db.list(who, limit, offset)
        base = _base(request, settings)
        return JobList(items=[s.job_out(j, base) for j in rows], total=total, limit=limit, offset=offset)

    @app.get("/v1/jobs/{job_id}", response_model=JobOut, tags=["jobs"], summary="a job", responses=problems)
    def get_job(job_id: str, request: Request, who: Annotated[str, Depends(owner)]) -> JobOut:
        s = svc()
        job = s.db.get(job_id, who)
        if job is None:
            raise Problem(404, "Not Found", f"no job {job_id} for this API key")
        return s.job_out(job, _base(request, settings))

    @app.delete(
        "/v1/jobs/{job_id}",
        status_code=204,
        tags=["jobs"],
        summary="cancel a job and delete its files",
        responses=problems,
    )
    def delete_job(job_id: str, who: Annotated[str, Depends(owner)]) -> Response:
        s = svc()
        job = s.db.get(job_id, who)
        if job is None:
            raise Problem(404, "Not Found", f"no job {job_id} for this API key")
        s.db.cancel(job_id)
        s.storage.delete_job(job_id)
        return Response(status_code=204)

    @app.get(
        "/v1/files/{token}",
        tags=["files"],
        summary="download an output through its signed link (no API key)",
        response_class=FileResponse,
        responses={403: {"model": ProblemBody}, 404: {"model": ProblemBody}},
    )
    def download(token: str) -> FileResponse:
        s = svc()
        try:
            job_id, name = tokens.verify(s.key, token)
        except tokens.BadToken as exc:
            raise Problem(403, "Forbidden", str(exc)) from None
        job = s.db.get(job_id)
        path = s.storage.output_path(job_id, name) if job is not None and job.state == "succeeded" else None
        if path is None:
            raise Problem(404, "Not Found", "this file no longer exists (the job was deleted)")
        media = OUTPUTS.get(name, ("file", "application/octet-stream"))[1]
        return FileResponse(path, media_type=media, filename=name, content_disposition_type="attachment")

    return app


def _parse_params(text: str | None) -> JobParams:
    if text is None or not text.strip():
        return JobParams()
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise Problem(422, "Unprocessable Content", f"params is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise Problem(422, "Unprocessable Content", "params must be a JSON object")
    try:
        params = JobParams.model_validate(data)
    except ValidationError as exc:
        errors = [
            {"field": ".".join(["params", *(str(p) for p in e["loc"])]).rstrip("."), "message": e["msg"]}
            for e in exc.errors()
        ]
        detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
        raise Problem(422, "Unprocessable Content", detail, errors=errors) from None
    try:
        params.engine_params()
    except ValueError as exc:
        errors = [{"field": "params", "message": str(exc)}]
        raise Problem(422, "Unprocessable Content", f"params: {exc}", errors=errors) from None
    return params


def _inspect(path: Any, filename: str | None) -> None:
    """Refuse at upload what can be seen then: not an archive, unsafe, too large, or nothing to build from."""
    from engine.errors import InputError
    from engine.io import inspect_input

    try:
        summary = inspect_input(path)
    except InputError as exc:
        detail = relabel(str(exc), filename)
        unreadable = ("neither an archive", "not a readable", "single 2-D image")
        status = 415 if any(s in detail for s in unreadable) else 422
        raise Problem(status, _title(status), detail) from None
    log.info("upload %s: %s", filename, summary)


def _base(request: Request, settings: Settings) -> str:
    return settings.public_url or str(request.base_url)


def _title(status: int) -> str:
    from http import HTTPStatus

    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"
