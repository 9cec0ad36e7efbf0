"""Strict, streaming ``multipart/form-data`` reader for job uploads.

The ``file`` part goes to an async sink in batches of about 4 MiB (the API writes them to storage off the event
loop), never held whole in memory: the batch is the received buffers themselves (views, not copies), and one batch
is written while the next is parsed. The small text field ``params`` is kept. The body must be complete: a missing
closing boundary, a part sent twice, or oversized part headers are 400s, never a silent default or "last one wins".
The uploaded file's name is client text: it is kept with its control characters escaped.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field

from python_multipart.multipart import MultipartParseError, MultipartParser, MultipartState, parse_options_header

from core.logsafe import escape_control

MAX_FIELD_BYTES = 64 << 10
MAX_HEADER_BYTES = 16 << 10
FLUSH_BYTES = 4 << 20
FIELDS = ("params", "callback_url")
Sink = Callable[[list[memoryview]], Awaitable[None]]  # awaited with the file's next buffers, in order


class UploadError(Exception):
    """A malformed request (status 400/415/422) with a reason."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


@dataclass
class ParsedUpload:
    """What the body held besides the file's bytes."""

    filename: str | None = None
    got_file: bool = False
    fields: dict[str, str] = field(default_factory=dict)


@dataclass
class _Part:
    headers: dict[bytes, bytes] = field(default_factory=dict)
    name: str | None = None
    buf: bytearray = field(default_factory=bytearray)
    hname: bytes = b""
    hvalue: bytes = b""
    header_bytes: int = 0


async def read_multipart(content_type: str, body: AsyncIterator[bytes], sink: Sink) -> ParsedUpload:
    """Parse the request body; the ``file`` part's bytes are awaited into ``sink`` in order.

    Raises:
        UploadError: not multipart (415), malformed or incomplete (400), unknown or missing parts (422).
    """
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data" or b"boundary" not in options:
        raise UploadError(415, "send the scan as multipart/form-data with a 'file' part (and optional 'params')")
    reader = _Reader()
    parser = MultipartParser(options[b"boundary"], reader.callbacks())
    writing: asyncio.Future[None] | None = None  # the batch being written while the next one is parsed

    async def flush() -> None:
        nonlocal writing
        if writing is not None:
            await writing
        batch = reader.take()
        writing = asyncio.ensure_future(sink(batch)) if batch else None

    try:
        try:
            async for chunk in body:
                parser.write(chunk)
                if reader.pending_bytes >= FLUSH_BYTES:
                    await flush()
            parser.finalize()
        except MultipartParseError as exc:
            raise UploadError(400, f"the multipart body is malformed: {exc}") from None
        if parser.state != MultipartState.END:
            raise UploadError(400, "the multipart body ends before its closing boundary: the upload is incomplete")
        await flush()
        if writing is not None:
            await writing
    finally:  # never leave a write running behind a refused or cancelled upload (its file is discarded next)
        if writing is not None and not writing.done():
            with contextlib.suppress(BaseException):
                await asyncio.shield(writing)
    if not reader.out.got_file:
        raise UploadError(422, "the 'file' part is missing: attach the scan archive as 'file'")
    return reader.out


class _Reader:
    """The parser's callbacks: each part's headers checked (known fields, each once, bounded headers), the text
    fields kept, and the file's bytes queued (``pending``) for the sink as views of the received chunks."""

    def __init__(self) -> None:
        self.out = ParsedUpload()
        self.part = _Part()
        self.pending: list[memoryview] = []  # file bytes parsed but not yet handed to the sink
        self.pending_bytes = 0
        self.seen: set[str] = set()

    def callbacks(self) -> dict[str, Callable[..., None]]:
        return {
            "on_part_begin": self.on_part_begin,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
        }

    def take(self) -> list[memoryview]:
        """The queued file bytes, handed over (the queue starts again empty)."""
        batch, self.pending, self.pending_bytes = self.pending, [], 0
        return batch

    def on_part_begin(self) -> None:
        self.part = _Part()

    def _header_bytes(self, n: int) -> None:
        self.part.header_bytes += n
        if self.part.header_bytes > MAX_HEADER_BYTES:
            raise UploadError(400, f"a part's headers are longer than {MAX_HEADER_BYTES:,} bytes")

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_bytes(end - start)
        self.part.hname += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_bytes(end - start)
        self.part.hvalue += data[start:end]

    def on_header_end(self) -> None:
        part = self.part
        part.headers[part.hname.lower()] = part.hvalue
        part.hname, part.hvalue = b"", b""

    def on_headers_finished(self) -> None:
        _, opts = parse_options_header(self.part.headers.get(b"content-disposition", b""))
        name = opts.get(b"name", b"").decode("utf-8", "replace")
        if name != "file" and name not in FIELDS:
            raise UploadError(
                422,
                f"unexpected form field {escape_control(name)!r}: send 'file', optionally 'params' and 'callback_url'",
            )
        if name in self.seen:
            raise UploadError(400, f"the form field {name!r} was sent twice: send each part once")
        self.seen.add(name)
        if name == "file":
            self.out.got_file = True
            raw = opts.get(b"filename")
            self.out.filename = escape_control(raw.decode("utf-8", "replace"))[-255:] if raw else None
        self.part.name = name

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        part = self.part
        if part.name == "file":
            view = memoryview(data)[start:end]  # the received chunk itself (immutable bytes), not a copy
            self.pending.append(view if isinstance(data, bytes) else memoryview(bytes(view)))
            self.pending_bytes += end - start
            return
        part.buf.extend(data[start:end])
        if len(part.buf) > MAX_FIELD_BYTES:
            raise UploadError(422, f"form field {part.name!r} is longer than {MAX_FIELD_BYTES:,} bytes")

    def on_part_end(self) -> None:
        part = self.part
        if part.name in FIELDS:
            try:
                self.out.fields[str(part.name)] = part.buf.decode("utf-8")
            except UnicodeDecodeError:
                raise UploadError(422, f"form field {part.name!r} is not UTF-8 text") from None
