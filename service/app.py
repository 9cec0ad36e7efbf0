"""The bonemesh REST API (FastAPI): upload a scan, follow the job, download the models through signed links, and
the web page that does all of it in a browser.

``create_app`` assembles the app from its parts: routers per resource (:mod:`service.routes`), dependencies
(:mod:`service.deps`), problem responses (:mod:`service.problems`), the services made in the lifespan
(:mod:`service.services`) and the background threads (:mod:`service.background`). The API records jobs in the
database, streams uploads to storage and enqueues by task name; it never imports Warp or the worker. Blocking work
(file writes, fsync, inspecting the archive, database writes, the broker) runs in threads: routes that do it are
``def``, and the upload's threads come from a small pool of their own, so a burst of uploads never queues the
status reads.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from typing import Any

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi
from fastapi.routing import APIRoute
from fastapi_offline import FastAPIOffline
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from core.settings import Settings, get_settings
from service import problems
from service.background import Background
from service.routes import direct, files, health, jobs, labels, page
from service.schemas import add_job_params
from service.services import Services

DESCRIPTION = (
    "Bone surface models from CT and micro-CT scans: upload a slice archive or DICOM series, get a watertight STL "
    "in millimetres for printing and light GLB models (metres) for phones and AR."
)
# what a browser client may send and read across origins
CORS_HEADERS = ["X-API-Key", "Content-Type", "If-None-Match", "Idempotency-Key"]
CORS_EXPOSED = [
    "Location",
    "ETag",
    "Content-Disposition",
    "Content-Length",
    "Cache-Control",
    "Retry-After",
    "Idempotent-Replayed",
]


# readable operation ids (generated clients' method names), by route function; others: the name in camelCase
OPERATION_IDS = {
    "healthz": "health",
    "readyz": "ready",
    "download": "downloadFile",
    "download_head": "headFile",
    "label_stl": "getLabelStl",
    "upload_options": "getUploadOptions",
    "begin_upload": "createUpload",
    "webhook_secret": "getWebhookSecret",
}


def operation_id(route: APIRoute) -> str:
    """The operation id of a route: ``createJob``, ``getJob``, ``listJobs``... (FastAPI's default is
    ``create_job_v1_jobs_post``)."""
    if route.name in OPERATION_IDS:
        return OPERATION_IDS[route.name]
    first, *rest = route.name.split("_")
    return first + "".join(word.capitalize() for word in rest)


def public_operations(schema: dict[str, Any]) -> dict[str, Any]:
    """Mark the operations that need no API key (health checks, signed downloads) with ``security: []``; the
    webhooks' answers are the receiver's (any 2xx, or anything else: retried), not FastAPI's validation error."""
    for ops in schema.get("paths", {}).values():
        for op in ops.values():
            op.setdefault("security", [])
    for ops in schema.get("webhooks", {}).values():
        for op in ops.values():
            op["responses"] = {
                "2XX": {"description": "any 2xx: delivered, not sent again"},
                "default": {"description": "any other status, or no answer in time: sent again later, with backoff"},
            }
    return schema


def page_csp(settings: Settings) -> str:
    """The page's Content-Security-Policy: scripts from this server only (no inline script, no eval; WebAssembly
    compiled for the Draco and meshopt decoders), workers from this server or blob: (three.js's Draco worker),
    fetches and images from this server (and the S3 store: direct uploads, ``download_links=store``), no framing."""
    store = ""
    if settings.storage_location()[0] == "s3":
        endpoint = settings.s3_endpoint_url
        store = " " + ("/".join(endpoint.split("/")[:3]) if endpoint else "https://*.amazonaws.com")
    return (
        "default-src 'none'; script-src 'self' 'wasm-unsafe-eval'; worker-src 'self' blob:; "
        f"connect-src 'self' blob: data:{store}; img-src 'self' blob: data:{store}; style-src 'self' 'unsafe-inline'; "
        "font-src 'self'; manifest-src 'self'; base-uri 'none'; form-action 'none'; object-src 'none'; "
        "frame-ancestors 'none'"
    )


class SecurityHeaders:
    """Every answer: ``nosniff`` and no Referer (download links carry their signature); the page (``/``): its CSP
    and no framing."""

    def __init__(self, app: ASGIApp, csp: str) -> None:
        self.app, self.csp = app, csp

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        is_page = scope.get("path") == "/"

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("x-content-type-options", "nosniff")
                headers.setdefault("referrer-policy", "no-referrer")
                if is_page:
                    headers["content-security-policy"] = self.csp
                    headers["x-frame-options"] = "DENY"
            await send(message)

        await self.app(scope, receive, send_with_headers)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API application (``uvicorn --factory service.app:create_app``)."""
    settings = settings or get_settings()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        svc = Services(settings)
        app.state.services = svc
        background = Background(svc)
        background.start()
        yield
        background.stop()
        svc.close()

    app = FastAPIOffline(  # /docs and /redoc with their scripts served from the package: no CDN
        title="bonemesh",
        version="1.0",
        description=DESCRIPTION,
        lifespan=lifespan,
        static_url="/docs/static",
        generate_unique_id_function=operation_id,
    )
    app.state.settings = settings
    app.state.data_dir = settings.data_dir
    problems.install(app)
    if settings.cors_origins:  # API keys travel in a header, never in cookies: no credentials, so no wildcard risk
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_credentials=False,
            allow_methods=["GET", "HEAD", "POST", "DELETE"],
            allow_headers=CORS_HEADERS,
            expose_headers=CORS_EXPOSED,
            max_age=600,
        )
    app.add_middleware(SecurityHeaders, csp=page_csp(settings))
    routers = (
        page.router,
        health.router,
        jobs.router,
        labels.router,
        jobs.webhooks_router,
        direct.router,
        files.router,
    )
    for router in routers:
        app.include_router(router)
    app.webhooks.include_router(jobs.callbacks)

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(
                title=app.title,
                version=app.version,
                description=app.description,
                routes=app.routes,
                webhooks=app.webhooks.routes,
            )
            app.openapi_schema = public_operations(add_job_params(problems.fix_openapi(schema)))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app
