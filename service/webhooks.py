"""Webhooks: a job may name a ``callback_url``; when it reaches a terminal state (succeeded, failed, cancelled)
the API POSTs the job resource there, signed as Standard Webhooks signs (``webhook-id``, ``webhook-timestamp``,
``webhook-signature: v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">``) with a secret per API key
(``GET /v1/webhook-secret``). A delivery that gets no 2xx is retried with exponential backoff
(``BONEMESH_WEBHOOK_BACKOFF_SECONDS``, doubling) until ``BONEMESH_WEBHOOK_RETRY_SECONDS`` after the job ended; every
attempt is recorded on the job (``webhook.attempts``). Redirects are not followed.

Callback URLs that resolve to loopback, link-local, private, multicast or reserved addresses are refused (SSRF),
when the job is created and again before every delivery (the name may resolve elsewhere by then), unless
``BONEMESH_WEBHOOK_ALLOW_PRIVATE`` is set. A delivery connects to an address that check passed, never resolving the
name again (a DNS answer that changes between the check and the connection, rebinding, cannot lead it to a private
address), while the request keeps the URL's name: its ``Host`` header, and for https its SNI and the certificate
check.
"""

from __future__ import annotations

import base64
import datetime as dt
import hashlib
import hmac
import http.client
import ipaddress
import socket
import ssl
import time
from typing import Any
from urllib.parse import urlsplit

from core.db import Job, utcnow
from core.logsafe import safe_logger

log = safe_logger("bonemesh.api")
SECRET_PREFIX = "whsec_"
LEASE_SECONDS = 60.0  # a delivery in progress is not taken by another API process for this long


class CallbackRefused(ValueError):
    """A callback URL the service will not call (the API answers 422)."""


def key_secret(server_key: bytes, owner: str) -> str:
    """The webhook secret of an API key's owner (derived from the server's key: stable, nothing stored)."""
    raw = hmac.new(server_key, f"webhook-secret/{owner}".encode(), hashlib.sha256).digest()
    return SECRET_PREFIX + base64.b64encode(raw).decode()


def sign(secret: str, msg_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` header value for ``body`` (Standard Webhooks, v1 = HMAC-SHA256)."""
    key = base64.b64decode(secret.removeprefix(SECRET_PREFIX))
    mac = hmac.new(key, f"{msg_id}.{timestamp}.".encode() + body, hashlib.sha256).digest()
    return "v1," + base64.b64encode(mac).decode()


def check_callback_url(url: str, allow_private: bool) -> str:
    """``url`` if the service may POST to it.

    Raises:
        CallbackRefused: not http(s), no host, credentials in it, does not resolve, or resolves to a loopback,
            link-local, private, multicast or reserved address while ``allow_private`` is off.
    """
    vetted_addresses(url, allow_private)
    return url


def vetted_addresses(url: str, allow_private: bool) -> list[str]:
    """The addresses ``url``'s host resolves to, each one checked (:func:`check_callback_url`): a delivery
    connects to these, never resolving the name again.

    Raises:
        CallbackRefused: as :func:`check_callback_url`.
    """
    if len(url) > 2048:
        raise CallbackRefused("callback_url is longer than 2048 characters")
    try:
        parts = urlsplit(url)
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError as exc:
        raise CallbackRefused(f"callback_url is not a URL: {exc}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise CallbackRefused("callback_url must be an http or https URL with a host")
    if parts.username or parts.password:
        raise CallbackRefused("callback_url must not carry credentials")
    try:
        infos = socket.getaddrinfo(parts.hostname, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        raise CallbackRefused(f"callback_url's host does not resolve ({exc})") from None
    addresses = list(dict.fromkeys(str(info[4][0]) for info in infos))
    if not allow_private:
        for address in addresses:
            addr = ipaddress.ip_address(address.split("%")[0])
            if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped:
                addr = addr.ipv4_mapped
            if not addr.is_global or addr.is_multicast:
                raise CallbackRefused(
                    f"callback_url resolves to {addr}, a loopback, link-local, private or reserved address"
                )
    if not addresses:
        raise CallbackRefused("callback_url's host resolves to no address")
    return addresses


def _connect_pinned(addresses: list[str], port: int, timeout: float | None) -> socket.socket:
    """A TCP connection to the first of ``addresses`` that answers (no name is resolved here)."""
    error: OSError | None = None
    for address in addresses:
        try:
            return socket.create_connection((address, port), timeout=timeout)
        except OSError as exc:
            error = exc
    raise error or OSError("no address to connect to")


class _PinnedHTTP(http.client.HTTPConnection):
    """HTTP to a vetted address; ``Host`` stays the URL's."""

    def __init__(self, host: str, port: int, addresses: list[str], timeout: float) -> None:
        super().__init__(host, port, timeout=timeout)
        self.addresses = addresses

    def connect(self) -> None:
        self.sock = _connect_pinned(self.addresses, self.port, self.timeout)


class _PinnedHTTPS(http.client.HTTPSConnection):
    """HTTPS to a vetted address; ``Host``, SNI and the certificate's name check stay the URL's host."""

    def __init__(
        self, host: str, port: int, addresses: list[str], timeout: float, context: ssl.SSLContext | None
    ) -> None:
        super().__init__(host, port, timeout=timeout, context=context or ssl.create_default_context())
        self.addresses = addresses

    def connect(self) -> None:
        sock = _connect_pinned(self.addresses, self.port, self.timeout)
        self.sock = self._context.wrap_socket(sock, server_hostname=self.host)  # type: ignore[attr-defined]


def post(
    url: str,
    body: bytes,
    headers: dict[str, str],
    timeout: float,
    addresses: list[str] | None = None,
    context: ssl.SSLContext | None = None,
) -> int:
    """POST ``body`` to ``url``, connecting to one of ``addresses`` (default: the name resolved now); the HTTP
    status (any status is returned, redirects are not followed; a network failure raises OSError)."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    port = parts.port or (443 if parts.scheme == "https" else 80)
    pinned = addresses or [str(info[4][0]) for info in socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)]
    conn: http.client.HTTPConnection
    if parts.scheme == "https":
        conn = _PinnedHTTPS(host, port, pinned, timeout, context)
    else:
        conn = _PinnedHTTP(host, port, pinned, timeout)
    target = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
    try:
        conn.request("POST", target, body=body, headers=headers)
        resp = conn.getresponse()
        resp.read(1 << 16)
        return int(resp.status)
    except http.client.HTTPException as exc:  # a malformed answer: a failed attempt, as a network error is
        raise OSError(f"the receiver's answer is not HTTP ({type(exc).__name__})") from None
    finally:
        conn.close()


def next_delay(attempt: int, backoff: float) -> float:
    """Seconds before retry number ``attempt`` (1-based): ``backoff * 2**(attempt-1)``, at most an hour."""
    return float(min(backoff * 2 ** min(attempt - 1, 30), 3600.0))


def deliver(services: Any, job: Job) -> str:
    """One delivery attempt of ``job``'s webhook, recorded on the job; returns the webhook's new state."""
    settings = services.settings
    body = services.job_out(job, settings.public_url or job.base_url or "").model_dump_json().encode()
    msg_id = f"msg_{job.id}_{job.state}"  # the same id on every retry, so receivers can drop duplicates
    timestamp = int(time.time())
    headers = {
        "content-type": "application/json",
        "user-agent": "bonemesh-webhooks",
        "webhook-id": msg_id,
        "webhook-timestamp": str(timestamp),
        "webhook-signature": sign(key_secret(services.key, job.owner), msg_id, timestamp, body),
    }
    status: int | None = None
    error: str | None = None
    try:
        addresses = vetted_addresses(job.callback_url or "", settings.webhook_allow_private)
        status = post(job.callback_url or "", body, headers, settings.webhook_timeout_seconds, addresses)
        if not 200 <= status < 300:
            error = f"the receiver answered {status}"
    except (OSError, CallbackRefused) as exc:
        error = f"{type(exc).__name__}: {exc}"[:300]
    now = utcnow()
    attempts = len(job.webhook_attempts or []) + 1
    attempt = {"at": now.replace(tzinfo=dt.UTC).isoformat(), "status": status, "error": error}
    if error is None:
        state, next_at = "delivered", None
    else:
        next_at = now + dt.timedelta(seconds=next_delay(attempts, settings.webhook_backoff_seconds))
        ended = job.finished_at or now
        give_up = next_at > ended + dt.timedelta(seconds=settings.webhook_retry_seconds)
        state, next_at = ("failed", None) if give_up else ("pending", next_at)
        log.info("job %s: webhook attempt %d failed (%s); %s", job.id, attempts, error, state)
    services.db.record_webhook(job.id, attempt, state, next_at)
    return state


def deliver_due(services: Any) -> int:
    """Deliver every due webhook once; returns how many attempts were made."""
    now = utcnow()
    made = 0
    for job in services.db.due_webhooks(now):
        if services.db.lease_webhook(job, now + dt.timedelta(seconds=LEASE_SECONDS)):
            deliver(services, job)
            made += 1
    return made
