"""Outages of what a job depends on, told from every other error: the database (PostgreSQL restarting, SQLite
locked past its timeout) and the object store (an S3 endpoint that refuses, drops or times out a connection, or
answers 5xx / SlowDown). They are transient: the API answers 503 with ``Retry-After`` and a problem type of its own,
and the worker retries with backoff (``retrying``) and re-queues a job the outage outlasts, failing it only after a
bounded time with ``database_unavailable`` / ``storage_unavailable``, never ``internal_error``.

A full disk is not an outage (``core.storage.is_storage_full``): it does not pass by waiting.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from core.logsafe import safe_logger

log = safe_logger("bonemesh.faults")
T = TypeVar("T")

DATABASE, STORAGE = "database", "storage"
CODES = {DATABASE: "database_unavailable", STORAGE: "storage_unavailable"}
# S3 answers that mean "not now" (the store is up but overloaded or restarting)
_S3_TRANSIENT = {"SlowDown", "ServiceUnavailable", "InternalError", "RequestTimeout", "503", "500", "502", "504"}
RETRY_AFTER_SECONDS = 5  # what the API's 503 asks a client to wait


@dataclass(frozen=True)
class Outage:
    """A dependency that is down for now: ``kind`` (``database`` or ``storage``), its error ``code``, and what was
    seen (the exception's type: no server address or path)."""

    kind: str
    seen: str

    @property
    def code(self) -> str:
        return CODES[self.kind]

    def message(self, doing: str = "") -> str:
        """A sentence for a client or a failed job."""
        what = "the job database" if self.kind == DATABASE else "the file store"
        during = f" while {doing}" if doing else ""
        return f"{what} was unreachable{during} ({self.seen}); nothing half-made was kept: try again shortly"


def outage_of(exc: BaseException) -> Outage | None:
    """The outage ``exc`` (or what caused it) reports, or None for any other error."""
    from core.storage import is_storage_full

    if is_storage_full(exc):
        return None
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        kind = _kind(cur)
        if kind is not None:
            return Outage(kind, type(cur).__name__)
        cur = cur.__cause__ or cur.__context__
    return None


def _kind(exc: BaseException) -> str | None:
    try:
        from sqlalchemy import exc as sa
    except ImportError:  # pragma: no cover - SQLAlchemy is a base dependency
        sa = None
    if sa is not None:
        if isinstance(exc, sa.DBAPIError) and exc.connection_invalidated:
            return DATABASE
        if isinstance(exc, sa.InterfaceError | sa.DisconnectionError | sa.TimeoutError):
            return DATABASE
        if isinstance(exc, sa.OperationalError):
            return DATABASE if _connection_lost(exc.orig) else None
    try:
        from botocore import exceptions as bc
    except ImportError:  # the s3 extra is not installed: no S3 store either
        return None
    if isinstance(exc, bc.ConnectionError | bc.HTTPClientError):
        return STORAGE
    if isinstance(exc, bc.ClientError):
        error = exc.response.get("Error", {}) if isinstance(exc.response, dict) else {}
        status = (exc.response.get("ResponseMetadata", {}) if isinstance(exc.response, dict) else {}).get(
            "HTTPStatusCode", 0
        )
        if str(error.get("Code", "")) in _S3_TRANSIENT or int(status or 0) >= 500:
            return STORAGE
    return None


def _connection_lost(orig: BaseException | None) -> bool:
    """Whether a driver's operational error is the server or the file being out of reach (PostgreSQL: every
    ``OperationalError`` is: refused, reset, shut down; SQLite: locked past its timeout, or not openable), not a
    statement the database refused."""
    import sqlite3

    if isinstance(orig, sqlite3.OperationalError):
        text = str(orig).lower()
        return any(w in text for w in ("locked", "unable to open", "disk i/o", "busy"))
    return orig is not None


def retrying(call: Callable[[], T], *, within: float, doing: str, first: float = 0.5, most: float = 8.0) -> T:
    """``call()``, tried again while it fails with an outage (``outage_of``), waiting ``first`` seconds, doubling up
    to ``most``, with jitter (a fleet of workers does not come back at once), for at most ``within`` seconds; then
    the outage's exception is raised. Any other error is raised at once."""
    deadline = time.monotonic() + within
    wait = first
    while True:
        try:
            return call()
        except Exception as exc:
            outage = outage_of(exc)
            left = deadline - time.monotonic()
            if outage is None or left <= 0:
                raise
            pause = min(wait, most, left) * random.uniform(0.5, 1.0)
            log.warning("%s: %s unreachable (%s); again in %.1f s", doing, outage.kind, outage.seen, pause)
            time.sleep(pause)
            wait *= 2
