"""A real HTTP gateway in front of Orthanc's DICOMweb, run in a thread of the test process, that misbehaves the way
hospital servers and gateways do. It forwards every request to Orthanc and passes the answer back, changed only
where a test asks for it (:meth:`DicomwebGate.reset` restores plain forwarding):

- ``default_accept``: WADO-RS asks Orthanc for its default transfer syntax (Explicit VR Little Endian), as a server
  that ignores ``transfer-syntax`` would; Orthanc then cuts a series answer short at the first instance it cannot
  transcode (JPEG 2000 here) and still answers 200, and cannot send that instance by itself either.
- ``refuse_any``: 406 for an Accept with ``transfer-syntax=*``.
- ``cut_series_after``: a series answer keeps its first n parts and half of the next one, then the connection
  closes (200, no closing boundary).
- ``repeat_parts``: every part of a series answer is sent twice.
- ``qido_cap``: a QIDO-RS answer holds at most n instances (the server's own cap; ``limit``/``offset`` honoured).
- ``qido_failures``: the next n QIDO-RS requests are answered 503.

``seen`` lists each request as (kind, Accept): kind is qido, series, instance or other.
"""

from __future__ import annotations

import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import httpx

from tests.service.procs import free_port

_SERIES = re.compile(r"/studies/[^/]+/series/[^/]+$")
_INSTANCE = re.compile(r"/studies/[^/]+/series/[^/]+/instances/[^/]+$")
_QIDO = re.compile(r"/instances$")


def _kind(method: str, path: str) -> str:
    if method == "GET":
        for kind, pattern in (("series", _SERIES), ("instance", _INSTANCE), ("qido", _QIDO)):
            if pattern.search(path):
                return kind
    return "other"


class DicomwebGate:
    """The gateway on a free loopback port, forwarding to ``upstream`` (Orthanc's DICOMweb root URL)."""

    def __init__(self, upstream: str) -> None:
        self.upstream = upstream.rstrip("/")
        self.port = free_port()
        self.lock = threading.Lock()
        self.reset()
        gate = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                gate.handle(self, "GET")

            def do_POST(self) -> None:
                gate.handle(self, "POST")

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, name="dicomweb-gate", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/dicom-web"

    def reset(self) -> None:
        with self.lock:
            self.default_accept = self.refuse_any = self.repeat_parts = False
            self.cut_series_after: int | None = None
            self.qido_cap: int | None = None
            self.qido_failures = 0
            self.seen: list[tuple[str, str]] = []

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    def handle(self, req: BaseHTTPRequestHandler, method: str) -> None:
        path, _, query = req.path.partition("?")
        sub = path.removeprefix("/dicom-web")
        accept = req.headers.get("Accept", "")
        kind = _kind(method, sub)
        with self.lock:
            self.seen.append((kind, accept))
            fail = kind == "qido" and self.qido_failures > 0
            self.qido_failures -= int(fail)
            refuse = kind in ("series", "instance") and self.refuse_any and "transfer-syntax=*" in accept
        if fail or refuse:
            return self._send(req, 503 if fail else 406, {"Content-Type": "text/plain"}, b"not now")
        params = dict(httpx.QueryParams(query))
        if kind == "qido" and self.qido_cap is not None:
            params["limit"] = str(min(int(params.get("limit", self.qido_cap)), self.qido_cap))
        headers = {k: v for k, v in req.headers.items() if k.lower() in ("accept", "content-type", "authorization")}
        if kind in ("series", "instance") and self.default_accept:
            headers["Accept"] = 'multipart/related; type="application/dicom"'
        body = req.rfile.read(int(req.headers.get("Content-Length", 0) or 0)) if method == "POST" else None
        up = httpx.request(method, self.upstream + sub, params=params, headers=headers, content=body, timeout=60)
        out = up.content
        if kind == "series" and up.status_code == 200 and (self.cut_series_after is not None or self.repeat_parts):
            out = self._rewrite(up.headers.get("Content-Type", ""), out)
        keep = {k: v for k, v in up.headers.items() if k.lower() in ("content-type", "warning")}
        self._send(req, up.status_code, keep, out, length=kind not in ("series", "instance"))

    def _rewrite(self, content_type: str, body: bytes) -> bytes:
        boundary = re.search(r'boundary="?([^";]+)', content_type)
        if boundary is None:
            return body
        delim = b"--" + boundary.group(1).encode()
        pieces = body.split(delim)
        parts = pieces[1:-1] if pieces[-1].startswith(b"--") else pieces[1:]
        if self.repeat_parts:
            return b"".join(delim + p for p in parts for _ in (0, 1)) + delim + b"--\r\n"
        n = self.cut_series_after or 0
        if n >= len(parts):
            return body
        return b"".join(delim + p for p in parts[:n]) + delim + parts[n][: len(parts[n]) // 2]

    @staticmethod
    def _send(
        req: BaseHTTPRequestHandler, status: int, headers: dict[str, str], body: bytes, length: bool = True
    ) -> None:
        """Answer; a WADO-RS body goes without Content-Length and ends when the connection closes (as Orthanc's)."""
        req.send_response(status)
        for key, value in headers.items():
            req.send_header(key, value)
        if length:
            req.send_header("Content-Length", str(len(body)))
        req.send_header("Connection", "close")
        req.end_headers()
        req.wfile.write(body)
