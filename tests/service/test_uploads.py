"""The streaming multipart reader on its own: the file's bytes reach the sink whole and in order whatever the
chunking, one batch is written while the next is parsed, and a refused body leaves no write running."""

from __future__ import annotations

import asyncio
import os

import pytest

from service.uploads import FLUSH_BYTES, UploadError, read_multipart

BOUNDARY = "b0nemesh"
CONTENT_TYPE = f"multipart/form-data; boundary={BOUNDARY}"


def _body(payload: bytes, *, close: bool = True) -> bytes:
    head = (
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="params"\r\n\r\n{{}}\r\n'
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="file"; filename="s.zip"\r\n'
        "Content-Type: application/zip\r\n\r\n"
    ).encode()
    return head + payload + (f"\r\n--{BOUNDARY}--\r\n".encode() if close else b"")


async def _chunks(body: bytes, sizes: list[int], sink: _Sink | None = None):
    i = k = 0
    while i < len(body):
        if sink is not None and sink.running:
            sink.overlapped = True
        n = sizes[k % len(sizes)]
        yield body[i : i + n]  # fresh bytes objects, as the server hands them on
        i, k = i + n, k + 1
        await asyncio.sleep(0)


class _Sink:
    """Records the batches; each write takes a little while (as a disk write in a thread), and notes whether it
    overlapped the parsing of later chunks."""

    def __init__(self, fail_after: int | None = None) -> None:
        self.data = bytearray()
        self.batches = 0
        self.running = 0
        self.fail_after = fail_after
        self.overlapped = False  # a chunk was received while a batch was being written

    async def __call__(self, batch: list[memoryview]) -> None:
        self.running += 1
        try:
            await asyncio.sleep(0.01)
            for view in batch:
                self.data += view
            self.batches += 1
            if self.fail_after is not None and self.batches > self.fail_after:
                raise OSError("disk full")
        finally:
            self.running -= 1


@pytest.mark.parametrize("sizes", [[65536], [1, 7, 4096, 100_003], [FLUSH_BYTES + 1]])
def test_file_reaches_the_sink_whole_and_in_order(sizes: list[int]) -> None:
    payload = os.urandom(2 * FLUSH_BYTES + 12_345)
    sink = _Sink()
    parsed = asyncio.run(read_multipart(CONTENT_TYPE, _chunks(_body(payload), sizes, sink), sink))
    assert bytes(sink.data) == payload
    assert sink.batches >= 2 and sink.running == 0
    assert sink.overlapped or sizes[0] > FLUSH_BYTES
    assert parsed.got_file and parsed.fields == {"params": "{}"} and parsed.filename == "s.zip"


def test_a_failed_write_fails_the_upload() -> None:
    sink = _Sink(fail_after=1)
    with pytest.raises(OSError, match="disk full"):
        asyncio.run(read_multipart(CONTENT_TYPE, _chunks(_body(os.urandom(5 * FLUSH_BYTES)), [65536]), sink))
    assert sink.running == 0


def test_a_cut_body_leaves_no_write_running() -> None:
    sink = _Sink()
    body = _body(os.urandom(3 * FLUSH_BYTES), close=False)
    with pytest.raises(UploadError, match="incomplete") as err:
        asyncio.run(read_multipart(CONTENT_TYPE, _chunks(body, [65536]), sink))
    assert err.value.status == 400
    assert sink.running == 0 and sink.batches >= 1
