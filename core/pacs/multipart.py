"""Reading a multipart/related body (RFC 2046) as it streams in, for WADO-RS: a part is given out only once the
boundary after it has arrived, so a body cut short (a dropped connection, a server that stops writing and still
answered 200) never passes a cut part on as whole, and the caller learns that the body was cut.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

CHUNK = 1 << 20


class MultipartError(ValueError):
    """The body is not a well-formed multipart body; ``cut``: it was cut short (worth asking again)."""

    def __init__(self, message: str, *, cut: bool) -> None:
        super().__init__(message)
        self.cut = cut


def response_parts(resp: Any) -> Iterator[bytes]:
    """The whole parts of a ``requests`` response (streamed) with a multipart/related body, or its body when it is
    one bare application/dicom instance; MultipartError (``cut``) after them when the body was cut short."""
    import requests

    media, _, rest = resp.headers.get("Content-Type", "").partition(";")
    media = media.strip().lower()
    try:
        if media == "application/dicom":  # one instance sent bare (not conformant, but seen)
            yield resp.content
            return
        boundary = header_param(rest, "boundary")
        if media != "multipart/related" or not boundary:
            raise MultipartError(f"unexpected answer ({media or 'no content type'})", cut=False)
        yield from split_multipart(resp.iter_content(CHUNK), boundary.encode())
    except requests.RequestException as exc:
        raise MultipartError(f"the answer was cut short ({type(exc).__name__})", cut=True) from None
    finally:
        resp.close()


def split_multipart(chunks: Iterable[bytes], boundary: bytes) -> Iterator[bytes]:
    """The contents of the parts of a multipart body (RFC 2046) arriving in ``chunks``; each is yielded once the
    next boundary is seen. MultipartError (``cut``) when the body ends before the closing boundary."""
    delim = b"\r\n--" + boundary
    buf = bytearray(b"\r\n")  # the first boundary may open the body
    pos, opened = 0, False
    for chunk in chunks:
        buf += chunk
        while True:
            i = buf.find(delim, pos)
            end = i + len(delim)
            if i < 0 or len(buf) < end + 2:
                pos = max(0, len(buf) - len(delim) - 2) if i < 0 else i
                break
            if opened:
                yield _content(bytes(buf[:i]))
            opened, closing = True, buf[end : end + 2] == b"--"
            del buf[:end]
            pos = 0
            if closing:
                return
    raise MultipartError("the multipart answer ended before its closing boundary", cut=True)


def _content(part: bytes) -> bytes:
    """The content of one part (its headers checked: application/dicom, the Content-Length when given)."""
    rest = part[2:] if part.startswith(b"\r\n") else b""
    if rest.startswith(b"\r\n"):  # a part without headers
        head, body = b"", rest[2:]
    else:
        head, sep, body = rest.partition(b"\r\n\r\n")
        if not sep:
            raise MultipartError("a malformed part in the multipart answer", cut=True)
    for line in head.decode("latin-1").split("\r\n"):
        name, _, value = line.partition(":")
        name, value = name.strip().lower(), value.strip()
        if name == "content-type" and value.split(";")[0].strip().lower() != "application/dicom":
            raise MultipartError(f"a part of type {value.split(';')[0]!r} in the answer", cut=False)
        if name == "content-length" and value.isdigit() and int(value) != len(body):
            raise MultipartError("a part shorter or longer than its Content-Length", cut=True)
    return body


def header_param(params: str, name: str) -> str | None:
    """The value of parameter ``name`` in the ``;``-separated parameters of a header (quotes removed)."""
    for item in params.split(";"):
        key, _, value = item.partition("=")
        if key.strip().lower() == name:
            return value.strip().strip('"')
    return None
