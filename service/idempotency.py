"""``Idempotency-Key`` on the requests that create something (``POST /v1/jobs``, ``POST /v1/uploads``), as the
IETF draft *The Idempotency-Key HTTP Header Field* describes it, so a client on a flaky network may send a request
again without making a second job:

* the first request with a key *holds* it (a row of ``idempotency_keys``, per API key: two keys never see each
  other's) while it runs; when it succeeds, the row records the request's *fingerprint* and what it made;
* the same key with the same request (the same file bytes, file name, params and callback, whatever the multipart
  boundary; the same JSON) answers what the first answered: the same job (its current state), with the first
  status, ``Location`` and ``Idempotent-Replayed: true``; nothing new is made;
* the same key with another request answers 422 (``urn:bonemesh:problem:idempotency_key_reused``);
* the same key while the first request still runs answers 409 (``idempotency_key_in_use``) with ``Retry-After``;
  a first request that stopped showing signs of life (:data:`STALE_SECONDS`: no body bytes arriving, no work
  going on; its process killed, its client gone) loses the key to the next one;
* a request that fails gives the key up: the same key may be sent again (with the mistake fixed);
* a key is remembered for ``BONEMESH_IDEMPOTENCY_TTL_SECONDS`` (default 24 h), and no longer than its job (deleting
  the job forgets the key); the API's background sweep removes expired keys.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import hashlib
import json
import time
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Annotated, Any

import anyio
from fastapi import Header

from core.db import IdempotencyKey, utcnow
from service.problems import Problem
from service.services import Services

JOBS = "POST /v1/jobs"
UPLOADS = "POST /v1/uploads"
STALE_SECONDS = 60.0  # a holder silent this long (no body bytes, no work) loses its key to the next request
BEAT_SECONDS = 10.0  # how often a holder that is alive says so
IN_USE_RETRY_SECONDS = 5
REPLAYED = "Idempotent-Replayed"
KEY_DESCRIPTION = (
    "a unique value (a UUID) per creation: sent again with the same request, it returns what the first made (the "
    "same job, with Idempotent-Replayed: true) instead of making another; with another request, 422. Remembered "
    "for BONEMESH_IDEMPOTENCY_TTL_SECONDS (default 24 h) and per API key"
)
KeyHeader = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        min_length=1,
        max_length=255,
        pattern=r"^[\x21-\x7e]([\x20-\x7e]*[\x21-\x7e])?$",
        description=KEY_DESCRIPTION,
    ),
]


def canonical(value: Any) -> str:
    """The SHA-256 of a JSON value with sorted keys and no spaces: equal for equal values."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def params_value(text: str | None) -> Any:
    """The ``params`` part as the value it names (its JSON), or its text when it is no JSON; None when empty."""
    if text is None or not text.strip():
        return None
    try:
        return json.loads(text)
    except (ValueError, RecursionError):
        return text


@dataclass
class UploadPrint:
    """The fingerprint of a multipart upload: its file's bytes (hashed as they are written, in the upload's
    threads), its file name and its text fields; never the boundary or the part order."""

    file: Any = field(default_factory=hashlib.sha256)
    fields: dict[str, Any] = field(default_factory=dict)

    def update(self, batch: list[memoryview]) -> None:
        for buf in batch:
            self.file.update(buf)

    def seal(self, filename: str | None, parts: dict[str, str]) -> None:
        self.fields = {
            "filename": filename,
            "params": params_value(parts.get("params")),
            "callback_url": (parts.get("callback_url") or "").strip() or None,
        }

    def hexdigest(self) -> str:
        return canonical({"kind": "multipart", "file_sha256": self.file.hexdigest(), **self.fields})


@dataclass
class Hold:
    """A key held by the request now running (``token``); ``progress()`` says it is alive (body bytes came)."""

    svc: Services
    owner: str
    scope: str
    key: str
    token: str
    last_sign: float = field(default_factory=time.monotonic)
    working: bool = False

    def progress(self) -> None:
        self.last_sign = time.monotonic()

    def _args(self) -> tuple[str, str, str, str]:
        return self.owner, self.scope, self.key, self.token

    def still_held(self) -> None:
        """Raise 409 when the key went to another request meanwhile (this one was silent too long)."""
        if not self.svc.db.touch_key(*self._args()):
            raise in_use(self.key)

    def finish(self, fingerprint: str, resource_id: str, status_code: int) -> None:
        self.svc.db.finish_key(*self._args(), fingerprint, resource_id, status_code)

    def release(self) -> None:
        self.svc.db.release_key(*self._args())

    async def beat(self) -> None:
        """Touch the key every :data:`BEAT_SECONDS` while the request shows signs of life (runs until cancelled)."""
        while True:
            await asyncio.sleep(BEAT_SECONDS)
            if self.working or time.monotonic() - self.last_sign < STALE_SECONDS:
                try:
                    await anyio.to_thread.run_sync(self.svc.db.touch_key, *self._args())
                except Exception:  # the database down for a moment: the next beat tries again
                    continue

    async def stream(self, body: AsyncIterator[bytes]) -> AsyncIterator[bytes]:
        """The request body, each chunk a sign of life."""
        async for chunk in body:
            self.progress()
            yield chunk


def in_use(key: str) -> Problem:
    return Problem(
        409,
        f"a request with Idempotency-Key {key!r} is still being carried out; send it again in a few seconds",
        code="idempotency_key_in_use",
        headers={"Retry-After": str(IN_USE_RETRY_SECONDS)},
    )


def reserve(svc: Services, owner: str, scope: str, key: str) -> Hold | IdempotencyKey:
    """Hold ``key`` for this request, or the row of the request that made something with it (blocking).

    Raises:
        Problem: 409 while the key's first request still runs.
    """
    token = uuid.uuid4().hex
    now = utcnow()
    expires = now + dt.timedelta(seconds=svc.settings.idempotency_ttl_seconds)
    stale = now - dt.timedelta(seconds=STALE_SECONDS)
    row = svc.db.reserve_key(owner, scope, key, token, expires, stale)
    if row is None:
        return Hold(svc, owner, scope, key, token)
    if row.state != "done" or row.resource_id is None:
        raise in_use(key)
    return row


def replayed(row: IdempotencyKey, fingerprint: str) -> str:
    """The id of what the key's first request made, when this request is the same.

    Raises:
        Problem: 422 when the key came with another request.
    """
    if row.fingerprint != fingerprint:
        raise Problem(
            422,
            f"Idempotency-Key {row.key!r} was used with another request (a different file, name, params or "
            "callback); send a new key with a new request",
            code="idempotency_key_reused",
            errors=[{"field": "Idempotency-Key", "message": "used before with another request"}],
        )
    return row.resource_id or ""


async def held(hold: Hold, work: Any) -> Any:
    """Await ``work`` (a coroutine) with ``hold`` kept alive; the key is given up when it fails."""
    beat = asyncio.ensure_future(hold.beat())
    try:
        return await work
    except BaseException:
        beat.cancel()
        with anyio.CancelScope(shield=True):
            try:
                await anyio.to_thread.run_sync(hold.release)
            except Exception:  # the database is down: the key goes stale, and the next request takes it
                pass
        raise
    finally:
        beat.cancel()
