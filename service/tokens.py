"""Signed, expiring download tokens: ``<payload>.<signature>``, both base64url, HMAC-SHA256 over the payload
``job_id/name/expires``. A token opens one file of one job until it expires, without the API key."""

from __future__ import annotations

import base64
import hashlib
import hmac
import time


class BadToken(Exception):
    """Forged, malformed or expired: every token that does not verify (the API answers all of them with 403)."""


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def sign(key: bytes, job_id: str, name: str, ttl_seconds: int, now: float | None = None) -> tuple[str, int]:
    """A token for ``name`` of ``job_id`` and its expiry (Unix seconds)."""
    expires = int((time.time() if now is None else now) + ttl_seconds)
    payload = _b64(f"{job_id}/{name}/{expires}".encode())
    sig = _b64(hmac.new(key, payload.encode(), hashlib.sha256).digest())
    return f"{payload}.{sig}", expires


def verify(key: bytes, token: str, now: float | None = None) -> tuple[str, str]:
    """``(job_id, name)`` of a valid token; BadToken otherwise."""
    try:
        payload, sig = token.split(".")
        expected = _b64(hmac.new(key, payload.encode(), hashlib.sha256).digest())
        if not hmac.compare_digest(sig.encode(), expected.encode()):  # bytes: any text compares, non-ASCII too
            raise BadToken("the link's signature does not match")
        job_id, name, expires = _unb64(payload).decode().split("/")
        expires_at = int(expires)
    except BadToken:
        raise
    except (ValueError, UnicodeDecodeError) as exc:
        raise BadToken("the link is malformed") from exc
    if (time.time() if now is None else now) > expires_at:
        raise BadToken("the link has expired; ask the API for the job again to get fresh links")
    return job_id, name


def expiry(token: str) -> int:
    """The expiry (Unix seconds) written in a token (call after ``verify``)."""
    try:
        return int(_unb64(token.split(".")[0]).decode().split("/")[2])
    except (ValueError, IndexError, UnicodeDecodeError) as exc:
        raise BadToken("the link is malformed") from exc
