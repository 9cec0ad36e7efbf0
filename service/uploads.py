"""Streaming ``multipart/form-data`` reader for job uploads: the ``file`` part goes straight into storage chunk
by chunk (never held whole in memory), small text fields (``params``) are kept, anything else is refused."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass, field

from python_multipart.multipart import MultipartParseError, MultipartParser, parse_options_header

from service.storage import UploadWriter

MAX_FIELD_BYTES = 64 << 10
FIELDS = ("params",)


class UploadError(Exception):
    """A malformed request (status 400/422) with a reason."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


@dataclass
class ParsedUpload:
    filename: str | None = None
    got_file: bool = False
    fields: dict[str, str] = field(default_factory=dict)


async def read_multipart(content_type: str, body: AsyncIterator[bytes], writer: UploadWriter) -> ParsedUpload:
    """Parse the request body; the ``file`` part is written to ``writer`` (not committed here)."""
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data" or b"boundary" not in options:
        raise UploadError(415, "send the scan as multipart/form-data with a 'file' part (and optional 'params')")
    out = ParsedUpload()
    state: dict[str, object] = {"headers": {}, "name": None, "buf": bytearray(), "hname": b"", "hvalue": b""}

    def on_part_begin() -> None:
        state["headers"], state["name"], state["buf"] = {}, None, bytearray()

    def on_header_field(data: bytes, start: int, end: int) -> None:
        state["hname"] = state["hname"] + data[start:end]  # type: ignore[operator]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        state["hvalue"] = state["hvalue"] + data[start:end]  # type: ignore[operator]

    def on_header_end() -> None:
        headers = state["headers"]
        assert isinstance(headers, dict)
        headers[bytes(state["hname"]).lower()] = bytes(state["hvalue"])  # type: ignore[arg-type]
        state["hname"], state["hvalue"] = b"", b""

    def on_headers_finished() -> None:
        headers = state["headers"]
        assert isinstance(headers, dict)
        _, opts = parse_options_header(headers.get(b"content-disposition", b""))
        name = opts.get(b"name", b"").decode("utf-8", "replace")
        if name != "file" and name not in FIELDS:
            raise UploadError(422, f"unexpected form field {name!r}: send 'file' and optionally 'params'")
        if name == "file":
            if out.got_file:
                raise UploadError(422, "send one 'file' per job")
            out.got_file = True
            raw = opts.get(b"filename")
            out.filename = raw.decode("utf-8", "replace")[-255:] if raw else None
        state["name"] = name

    def on_part_data(data: bytes, start: int, end: int) -> None:
        if state["name"] == "file":
            writer.write(data[start:end])
            return
        buf = state["buf"]
        assert isinstance(buf, bytearray)
        buf.extend(data[start:end])
        if len(buf) > MAX_FIELD_BYTES:
            raise UploadError(422, f"form field {state['name']!r} is longer than {MAX_FIELD_BYTES:,} bytes")

    def on_part_end() -> None:
        name = state["name"]
        if name in FIELDS:
            buf = state["buf"]
            assert isinstance(buf, bytearray)
            try:
                out.fields[str(name)] = buf.decode("utf-8")
            except UnicodeDecodeError:
                raise UploadError(422, f"form field {name!r} is not UTF-8 text") from None

    parser = MultipartParser(
        options[b"boundary"],
        {
            "on_part_begin": on_part_begin,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
        },
    )
    try:
        async for chunk in body:
            parser.write(chunk)
        parser.finalize()
    except MultipartParseError as exc:
        raise UploadError(400, f"the multipart body is malformed: {exc}") from None
    if not out.got_file:
        raise UploadError(422, "the 'file' part is missing: attach the scan archive as 'file'")
    return out


def relabel(message: str, filename: str | None) -> str:
    """An engine message about the stored upload (named ``upload``) in terms of the client's file name."""
    name = filename or "the upload"
    return message.replace("upload", name, 1) if message.startswith("upload") else message
