"""DICOMweb retries (``core.pacs.dicomweb``) honour the server's ``Retry-After`` (seconds or an HTTP date, up to a
cap) and add jitter to their exponential backoff; tested on the formulas and against a real HTTP server that
answers 429 / 503 with Retry-After before it answers the QIDO-RS search."""

from __future__ import annotations

import datetime as dt
import json
import threading
from collections.abc import Iterator
from email.utils import format_datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest

from core.pacs import dicomweb
from core.pacs.config import DicomwebServer
from core.pacs.dicomweb import MAX_RETRY_AFTER, DicomwebError, parse_retry_after, retry_delay


def test_retry_after_is_read_as_seconds_or_a_date() -> None:
    now = dt.datetime(2026, 1, 1, 12, 0, 0, tzinfo=dt.UTC)
    assert parse_retry_after("7") == 7.0
    assert parse_retry_after(format_datetime(now + dt.timedelta(seconds=30), usegmt=True), now) == 30.0
    assert parse_retry_after(format_datetime(now - dt.timedelta(seconds=30), usegmt=True), now) == 0.0
    assert parse_retry_after("100000") == MAX_RETRY_AFTER
    for unreadable in (None, "", "soon", "-3", "1.5"):
        assert parse_retry_after(unreadable) is None, unreadable


def test_backoff_has_jitter_and_never_undercuts_retry_after() -> None:
    server = DicomwebServer(url="http://pacs.test", backoff_seconds=2.0, attempts=5)
    for attempt, base in ((1, 2.0), (2, 4.0), (3, 8.0)):
        delays = [retry_delay(server, attempt) for _ in range(200)]
        assert all(base / 2 <= d <= base for d in delays), (attempt, min(delays), max(delays))
        assert len({round(d, 6) for d in delays}) > 100  # spread, not one value
    told = DicomwebError("HTTP 503", transient=True, status=503, retry_after=10.0)
    delays = [retry_delay(server, 1, told) for _ in range(100)]
    assert all(10.0 <= d <= 11.0 for d in delays) and len(set(delays)) > 50
    short = DicomwebError("HTTP 429", transient=True, status=429, retry_after=0.0)
    assert all(4.0 <= retry_delay(server, 3, short) <= 8.0 for _ in range(50))  # backoff when it asks less


@pytest.fixture
def busy_pacs() -> Iterator[tuple[str, list[str]]]:
    """A QIDO-RS endpoint that answers 429 (Retry-After: 2 s), then 503 (Retry-After: an HTTP date 1 s on), then
    the list."""
    calls: list[str] = []

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            calls.append(self.path)
            if len(calls) == 1:
                self._answer(429, b"", {"Retry-After": "2"})
            elif len(calls) == 2:
                when = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=1)
                self._answer(503, b"", {"Retry-After": format_datetime(when, usegmt=True)})
            else:
                body = json.dumps([{"00080018": {"vr": "UI", "Value": ["1.2.3.4.5"]}}]).encode()
                self._answer(200, body if len(calls) == 3 else b"[]", {"Content-Type": "application/dicom+json"})

        def _answer(self, status: int, body: bytes, headers: dict[str, str]) -> None:
            self.send_response(status)
            for name, value in {**headers, "Content-Length": str(len(body))}.items():
                self.send_header(name, value)
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}", calls
    server.shutdown()
    server.server_close()


def test_a_busy_server_is_asked_again_after_its_retry_after(
    busy_pacs: tuple[str, list[str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    url, calls = busy_pacs
    slept: list[float] = []
    monkeypatch.setattr(dicomweb.time, "sleep", slept.append)  # the waits asked for, not waited
    server = DicomwebServer(url=url, attempts=3, backoff_seconds=0.1)
    session = dicomweb.session_for(server)
    try:
        base = f"{url}/studies/1.2/series/1.2.3"
        assert dicomweb.list_instances(dicomweb._Qido(session, server, base)) == ["1.2.3.4.5"]
    finally:
        session.close()
    assert len(calls) == 4 and all(c.startswith("/studies/1.2/series/1.2.3/instances") for c in calls)
    first, second = slept
    assert 2.0 <= first <= 2.1, slept  # Retry-After: 2 (plus jitter up to half the 0.1 s backoff)
    assert 0.0 <= second <= 1.3 and second >= 0.1, slept  # the date, about 1 s on; never under the backoff
