"""Liveness and readiness probes."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.deps import ServicesDep
from service.schemas import Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="the process is up")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get(
    "/readyz",
    summary="database, Redis and storage are reachable",
    response_model=Readiness,
    responses={503: {"model": Readiness, "description": "a dependency is unreachable (status 'not ready')"}},
)
def readyz(svc: ServicesDep) -> JSONResponse:
    checks: dict[str, str] = {}
    for name, probe in (("database", svc.db.ping), ("redis", svc.queue.ping), ("storage", svc.storage.ping)):
        try:
            probe()
            checks[name] = "ok"
        except Exception as exc:
            checks[name] = f"unreachable: {type(exc).__name__}: {exc}"
    ready = all(v == "ok" for v in checks.values())
    return JSONResponse({"status": "ready" if ready else "not ready", "checks": checks}, 200 if ready else 503)
