"""Errors as ``application/problem+json`` (RFC 9457), for every way a request can end badly, and the OpenAPI
document saying so: every 4xx/5xx response of every operation is declared with the problem media type only.

Three layers answer: ``Problem`` raised by the routes, the handlers of Starlette's HTTP errors (404 of unknown
paths, 405 with the complete ``Allow`` list) and of request validation (422), and ``LastResort``, an ASGI
middleware that turns anything unexpected into a 500 problem without the traceback (which is logged, escaped).
"""

from __future__ import annotations

from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from core.faults import RETRY_AFTER_SECONDS, Outage, outage_of
from core.logsafe import escape_control, safe_logger

log = safe_logger("bonemesh.api")
PROBLEM = "application/problem+json"
PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}
METHODS = ("DELETE", "GET", "HEAD", "PATCH", "POST", "PUT")


class Problem(Exception):
    """An error answered as application/problem+json; ``detail`` is escaped (it may quote client text). ``code``
    (one of :data:`CODES`; default: the status's) names the problem type, ``urn:bonemesh:problem:<code>``."""

    def __init__(
        self,
        status: int,
        detail: str,
        *,
        title: str | None = None,
        code: str | None = None,
        headers: dict[str, str] | None = None,
        **extra: Any,
    ) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail, self.extra = status, title or title_of(status), detail, extra
        self.code, self.headers = code or code_of(status), headers


# every problem type the API answers with: code -> (status, what it means); docs/api.md has the same table
CODES: dict[str, tuple[int, str]] = {
    "bad_request": (400, "the request is malformed: a multipart body cut short or a part sent twice, invalid JSON"),
    "unauthorized": (401, "no API key, or one this service does not know (send it in X-API-Key)"),
    "link_invalid": (403, "a download link that does not verify: forged, malformed or expired"),
    "not_found": (404, "no such job, upload, file or path for this API key"),
    "method_not_allowed": (405, "the path exists, the method does not (Allow lists those that do)"),
    "conflict": (409, "the resource is not in a state that allows it (a job already finished, an upload completing)"),
    "idempotency_key_in_use": (
        409,
        "a request with this Idempotency-Key is still being carried out; send it again after Retry-After",
    ),
    "too_large": (413, "the upload or the request body is larger than the limit"),
    "unsupported_media_type": (415, "not multipart/form-data or JSON, or an archive bonemesh does not read"),
    "invalid_request": (422, "a field is invalid (errors[] names each one); or an archive that cannot be a scan"),
    "callback_refused": (
        422,
        "callback_url is not one the service will call: not http(s), credentials in it, or a private address",
    ),
    "upload_incomplete": (
        422,
        "a direct upload's parts are missing, short or not those sent (it stays open: send them, then complete)",
    ),
    "idempotency_key_reused": (
        422,
        "this Idempotency-Key was used with another request body; use a new key for a new request",
    ),
    "internal_error": (500, "the server met an unexpected error (logged; the request was not carried out)"),
    "queue_unavailable": (503, "the job queue (Redis) is unreachable; nothing changed, send the request again"),
    "database_unavailable": (503, "the job database is unreachable for the moment; nothing was done (Retry-After)"),
    "storage_unavailable": (503, "the file store is unreachable for the moment; nothing was done (Retry-After)"),
    "unavailable": (503, "the service cannot answer for the moment; send the request again later"),
    "storage_full": (507, "the data volume cannot hold the upload; nothing was kept"),
}
_BY_STATUS = {400: "bad_request", 401: "unauthorized", 403: "link_invalid", 404: "not_found"}
_BY_STATUS |= {405: "method_not_allowed", 409: "conflict", 413: "too_large", 415: "unsupported_media_type"}
_BY_STATUS |= {422: "invalid_request", 500: "internal_error", 503: "unavailable", 507: "storage_full"}


def code_of(status: int) -> str:
    """The problem code of a status when nothing more precise is known."""
    return _BY_STATUS.get(status, "bad_request" if status < 500 else "internal_error")


class ProblemBody(BaseModel):
    """An RFC 9457 problem document. ``type`` is ``urn:bonemesh:problem:<code>``, one per ``code`` (the table of
    codes is in docs/api.md); clients tell problems apart by ``code`` (or ``type``), never by ``detail``."""

    type: str = Field(description="urn:bonemesh:problem:<code>: a stable URI naming the kind of problem")
    title: str
    status: int
    detail: str
    code: str = Field(description="the problem's code: " + ", ".join(CODES))
    errors: list[dict[str, Any]] | None = None


# RFC 9110's reason phrases where Python's differ by version (3.13 took them up: "Unprocessable Content" was
# "Unprocessable Entity"), so titles and the OpenAPI document are the same on every Python
_RFC9110 = {413: "Content Too Large", 414: "URI Too Long", 416: "Range Not Satisfiable", 422: "Unprocessable Content"}


def title_of(status: int) -> str:
    """The reason phrase of an HTTP status (RFC 9110's)."""
    if status in _RFC9110:
        return _RFC9110[status]
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def problem_type(code: str) -> str:
    """The stable URI of a problem type (``urn:bonemesh:problem:<code>``, listed in docs/api.md)."""
    return f"urn:bonemesh:problem:{code}"


def problem_response(
    status: int,
    detail: str,
    *,
    title: str | None = None,
    headers: dict[str, str] | None = None,
    code: str | None = None,
    **extra: Any,
) -> JSONResponse:
    """A problem+json response of type ``urn:bonemesh:problem:<code>`` (``code``: the status's by default)."""
    code = code or code_of(status)
    body = {"type": problem_type(code), "title": title or title_of(status), "status": status}
    body |= {"detail": escape_control(detail), "code": code}
    return JSONResponse({**body, **extra}, status_code=status, media_type=PROBLEM, headers=headers)


def problems(*codes: int, **descriptions: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for error statuses (the content is set to problem+json by ``fix_openapi``);
    ``descriptions`` are keyed ``d<status>`` (``d413="the upload is larger than the limit"``)."""
    return {code: {"description": descriptions.get(f"d{code}", title_of(code))} for code in codes}


def allowed_methods(app: FastAPI, scope: Scope) -> list[str]:
    """Every method some route accepts on the request's path (for ``Allow``): each method is tried against the
    routes (routers included through ``include_router`` answer ``matches`` as their routes do)."""
    allowed = []
    for method in METHODS:
        probe = {**scope, "method": method}
        if any(route.matches(probe)[0] is Match.FULL for route in app.router.routes):
            allowed.append(method)
    return allowed


def install(app: FastAPI) -> None:
    """The exception handlers and the last-resort middleware."""

    @app.exception_handler(Problem)
    async def _problem(_: Request, exc: Problem) -> JSONResponse:
        return problem_response(
            exc.status, exc.detail, title=exc.title, headers=exc.headers, code=exc.code, **exc.extra
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(allowed_methods(app, request.scope))
        return problem_response(exc.status_code, str(exc.detail), headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"field": ".".join(str(p) for p in e["loc"]), "message": e["msg"]} for e in exc.errors()]
        detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
        return problem_response(422, detail, errors=errors)

    app.add_middleware(LastResort)


class LastResort:
    """ASGI middleware: an exception no handler took becomes a problem+json 500 (logged here, not re-raised, so the
    server logs no raw traceback with client text in it)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def _send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, _send)
        except Exception as exc:
            if isinstance(exc, ClientDisconnect):  # the client went away mid-body: nobody to answer, nothing kept
                log.info(
                    "%s %s: the client went away before the whole request came", scope.get("method"), scope.get("path")
                )
                return
            outage = outage_of(exc)
            if outage is not None:  # transient: the database or the store is down for now (core.faults)
                log.warning(
                    "%s %s: %s unreachable (%s)", scope.get("method"), scope.get("path"), outage.kind, outage.seen
                )
                if not started:
                    await outage_response(outage)(scope, receive, send)
                return
            log.exception("unexpected error answering %s %s", scope.get("method"), scope.get("path"))
            if not started:
                detail = "the server met an unexpected error; it is logged, and the request was not carried out"
                await problem_response(500, detail)(scope, receive, send)


def outage_response(outage: Outage) -> JSONResponse:
    """503 with ``Retry-After`` and the outage's own problem type (``database_unavailable``, ``storage_unavailable``):
    nothing was done, the same request can be sent again."""
    what = "the job database" if outage.kind == "database" else "the file store"
    return problem_response(
        503,
        f"{what} is unreachable for the moment ({outage.seen}); nothing was done: try again in {RETRY_AFTER_SECONDS} s",
        headers={"Retry-After": str(RETRY_AFTER_SECONDS)},
        code=outage.code,
    )


OUTAGE_DESCRIPTION = (
    "the job database or the file store is unreachable for the moment (problem type "
    "urn:bonemesh:problem:database_unavailable or urn:bonemesh:problem:storage_unavailable); nothing was done"
)
RETRY_AFTER_HEADER = {
    "Retry-After": {"description": "seconds to wait before sending the same request", "schema": {"type": "integer"}}
}


def fix_openapi(schema: dict[str, Any]) -> dict[str, Any]:
    """Declare every error response as problem+json (FastAPI writes application/json), add the last-resort 500 and
    the outage's 503 (with ``Retry-After``) to every operation, and drop the validation-error schemas FastAPI adds
    (the 422s are problems too)."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components["Problem"] = ProblemBody.model_json_schema()
    for ops in schema.get("paths", {}).values():
        for op in ops.values():
            responses = op.setdefault("responses", {})
            responses.setdefault("500", {"description": "unexpected error (problem document, no traceback)"})
            if not op.get("operationId", "").startswith(("health", "ready", "live")):
                responses.setdefault("503", {"description": OUTAGE_DESCRIPTION, "headers": RETRY_AFTER_HEADER})
            for code, response in responses.items():
                if code[0] in "45" and _generated(response.get("content")):
                    response["content"] = {PROBLEM: {"schema": PROBLEM_REF}}
                    if response.get("description") in ("Validation Error", "Successful Response"):
                        response["description"] = title_of(int(code))
    for name in ("HTTPValidationError", "ValidationError", "ProblemBody"):
        components.pop(name, None)
    return schema


def _generated(content: dict[str, Any] | None) -> bool:
    """Whether a response's content is FastAPI's default (none, or the validation/problem model as JSON) rather
    than one a route declared on purpose (e.g. the readiness document of a 503)."""
    if not content:
        return True
    ref = content.get("application/json", {}).get("schema", {}).get("$ref", "")
    return set(content) == {"application/json"} and ref.rsplit("/", 1)[-1] in ("HTTPValidationError", "ProblemBody")
