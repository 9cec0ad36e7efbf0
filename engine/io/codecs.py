"""Fast decoders for the commonest slice format, used where they give exactly what the general path gives.

A 16- or 8-bit grayscale PNG (colour type 0, no transparency chunk: what CT exporters write) is decoded with
``imagecodecs.png_decode`` (libpng), which holds no GIL while it inflates and unfilters, so it scales with the
threads of ``engine.io.parallel``; Pillow's PNG reader runs its chunk loop in Python and scales less. Everything
else (palette, colour, alpha, 1/2/4-bit PNG, JPEG, BMP), and every PNG when imagecodecs is not installed, goes
through imageio/Pillow as before. Both give the stored values as uint8/uint16 (tests check they agree).

libpng inflates with zlib, which is most of its time on a CT slice. So a non-interlaced slice's zlib stream is
first inflated with libdeflate (``imagecodecs.deflate_decode``, about twice zlib's speed) into exactly the filtered
rows the header implies, written back as an uncompressed ("stored") zlib stream, and libpng decodes the PNG with
that one IDAT in place of the original ones: its inflate is then a copy, its unfiltering and everything else as
before, so the samples are libpng's (every filter type, every ancillary chunk kept in place). The temporaries live
in per-thread scratch buffers (fresh 2 MB buffers per slice cost more in page faults than the inflate saves). A
1024 x 1024 16-bit phantom slice: 9.2 ms instead of 13 ms; a 160-slice stack on 2 threads, each load in a fresh
process (``benchmarks.ingest``): 0.81-0.83 s instead of 1.05-1.08 s. A stream that does not inflate to exactly those
rows (damaged, short, padded) is decoded from the original bytes, so libpng reports it as before. The loader hands
each slice its plane of the volume, and libpng writes the samples there (no temporary slice, no copy: 8 % less CPU
for a 160 x 1024 x 1024 stack here).
"""

from __future__ import annotations

import struct
import threading
import zlib
from typing import Any

import numpy as np

USE_IMAGECODECS = True  # benchmarks switch it off to time the general path
_SCRATCH = threading.local()


def _imagecodecs() -> object | None:
    try:
        import imagecodecs
    except ImportError:
        return None
    return imagecodecs if imagecodecs.PNG.available else None


def plain_gray_png(data: bytes) -> bool:
    """Whether PNG bytes hold an 8- or 16-bit grayscale image without a transparency chunk."""
    if len(data) < 33 or data[12:16] != b"IHDR" or data[25] != 0 or data[24] not in (8, 16):
        return False
    idat = data.find(b"IDAT")
    return idat > 0 and b"tRNS" not in data[:idat]


def decode_png_fast(data: bytes, out: np.ndarray | None = None) -> np.ndarray | None:
    """The (y, x) array of a plain grayscale PNG through libpng; None when the general path must decode it.

    ``out``: a C-contiguous (y, x) array to decode into where the header gives that shape and sample type (a plane of
    the volume being loaded: no temporary slice, no copy); the result is then ``out`` itself. Otherwise, or where
    the header differs, a new array."""
    if not USE_IMAGECODECS or not plain_gray_png(data):
        return None
    codecs = _imagecodecs()
    if codecs is None:
        return None
    width, height, depth = struct.unpack(">IIB", data[16:25])
    dtype = np.uint8 if depth == 8 else np.uint16
    into = out is not None and out.shape == (height, width) and out.dtype == dtype and out.flags.c_contiguous
    arr = codecs.png_decode(_stored(codecs, data) or data, out=out if into else None)  # type: ignore[attr-defined]
    return arr if arr.ndim == 2 and arr.dtype in (np.uint8, np.uint16) else None


def _scratch(name: str, size: int) -> memoryview:
    """A reusable buffer of this thread's, at least ``size`` bytes (grown, never shrunk, while the thread lives:
    the decode pool's threads end with their load), so that each slice's temporaries touch no fresh pages."""
    buf = getattr(_SCRATCH, name, None)
    if buf is None or len(buf) < size:
        buf = bytearray(size)
        setattr(_SCRATCH, name, buf)
    return memoryview(buf)[:size]


def _stored(codecs: object, data: bytes) -> memoryview | None:
    """``data`` (a plain grayscale PNG) with its IDAT chunks replaced by one holding the same rows as a stored zlib
    stream (inflated with libdeflate), in this thread's scratch buffer (valid until its next call); None when it is
    interlaced, its chunks are malformed, or the stream does not inflate to exactly the rows its header gives
    (then libpng decodes the original)."""
    width, height, depth, interlace = struct.unpack(">IIB3xB", data[16:29])
    if interlace or not width or not height:
        return None
    size = height * (1 + width * depth // 8)
    chunks = _chunks(data)
    if chunks is None:
        return None
    head, parts, tail = chunks
    rows = _inflated(codecs, parts, _scratch("rows", size))
    if rows is None:
        return None
    return _with_stored_idat(codecs, head, rows, tail)


def _with_stored_idat(codecs: object, head: list[memoryview], rows: memoryview, tail: list[memoryview]) -> memoryview:
    """A PNG of the chunks ``head``, one IDAT holding ``rows`` as a stored zlib stream, and the chunks ``tail``, in
    this thread's scratch buffer (valid until its next call)."""
    size = len(rows)
    bound = size + (size >> 12) + (size >> 14) + (size >> 25) + 13  # zlib's compressBound
    before, after = sum(len(c) for c in head), sum(len(c) for c in tail)
    png = _scratch("png", before + 12 + bound + after)
    at = _put(png, 0, head) + 8
    stored = len(codecs.zlib_encode(rows, level=0, out=png[at : at + bound]))  # type: ignore[attr-defined]
    png[at - 8 : at] = struct.pack(">I", stored) + b"IDAT"
    png[at + stored : at + stored + 4] = struct.pack(">I", zlib.crc32(png[at - 4 : at + stored]))
    return png[: _put(png, at + stored + 4, tail)]


def _chunk(kind: bytes, data: bytes) -> memoryview:
    return memoryview(struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data)))


def rows_bytes(shape: tuple[int, int], dtype: np.dtype[Any]) -> int:
    """The size of a grayscale PNG's filtered rows: each row's filter-type byte, then its samples."""
    return shape[0] * (1 + shape[1] * np.dtype(dtype).itemsize)


def filters_known(rows: memoryview, shape: tuple[int, int], dtype: np.dtype[Any]) -> bool:
    """Whether every row of ``rows`` (``inflate_rows``' output) names a filter type PNG defines (0-4), as libpng
    and the device's unfiltering (``engine.io.png_rows``) require."""
    width = 1 + shape[1] * np.dtype(dtype).itemsize
    return int(np.frombuffer(rows, np.uint8)[::width].max(initial=0)) <= 4


def can_unfilter() -> bool:
    """Whether ``unfilter_rows`` can run here (imagecodecs' libpng is installed)."""
    return _imagecodecs() is not None


def unfilter_rows(rows: memoryview, shape: tuple[int, int], dtype: np.dtype[Any], out: np.ndarray) -> bool:
    """Undo the row filters of ``rows`` (a grayscale, non-interlaced PNG's inflated rows, ``inflate_rows``) on the
    host, into ``out`` ((y, x) of ``dtype``, C-contiguous): libpng unfilters them from a PNG made around them, as
    it does for a slice it decodes. False where imagecodecs is missing, the rows are not of that shape and type, or
    libpng refuses them (a filter type PNG does not define)."""
    codecs = _imagecodecs()
    dtype = np.dtype(dtype)
    if codecs is None or len(rows) != rows_bytes(shape, dtype) or out.shape != shape or out.dtype != dtype:
        return False
    header = struct.pack(">IIBBBBB", shape[1], shape[0], 8 * dtype.itemsize, 0, 0, 0, 0)  # grayscale
    head = [memoryview(b"\x89PNG\r\n\x1a\n"), _chunk(b"IHDR", header)]
    png = _with_stored_idat(codecs, head, rows, [_chunk(b"IEND", b"")])
    try:
        arr = codecs.png_decode(png, out=out)  # type: ignore[attr-defined]
    except Exception:  # a filter type PNG does not define
        return False
    return arr is out or bool(np.shares_memory(arr, out))


def inflate_rows(data: bytes, shape: tuple[int, int], dtype: np.dtype[Any], out: memoryview) -> bool:
    """Inflate a plain grayscale, non-interlaced PNG of ``shape`` (y, x) and ``dtype`` (uint8 or uint16) into
    ``out``: exactly its filtered rows (each row's filter-type byte, then its big-endian samples as filtered), for
    a device to unfilter (``engine.io.png_rows``). False, with ``out`` in any state, where the PNG is of another
    kind, shape or type, its chunks are malformed, imagecodecs is missing, or the stream does not inflate to exactly
    ``len(out)`` bytes: the caller then decodes it the usual way (which reports what is wrong)."""
    if not USE_IMAGECODECS or not plain_gray_png(data):
        return False
    width, height, depth, interlace = struct.unpack(">IIB3xB", data[16:29])
    if interlace or (height, width) != shape or depth != 8 * np.dtype(dtype).itemsize:
        return False
    codecs = _imagecodecs()
    chunks = _chunks(data) if codecs is not None and len(out) == height * (1 + width * depth // 8) else None
    return chunks is not None and _inflated(codecs, chunks[1], out) is not None


def _chunks(data: bytes) -> tuple[list[memoryview], list[memoryview], list[memoryview]] | None:
    """A PNG's chunks: those before its IDAT chunks (with the signature), the IDAT chunks' data, those after; None
    where a chunk runs past the end, IDAT chunks are not consecutive, or there is none."""
    view = memoryview(data)
    head, parts, tail = [view[:8]], [], []
    pos = 8
    while pos + 12 <= len(data):
        (length,) = struct.unpack(">I", view[pos : pos + 4])
        end = pos + 12 + length
        if end > len(data):
            return None
        if view[pos + 4 : pos + 8] == b"IDAT":
            if tail:
                return None  # IDAT chunks must be consecutive
            parts.append(view[pos + 8 : end - 4])
        else:
            (tail if parts else head).append(view[pos:end])
        pos = end
    return (head, parts, tail) if parts else None


def _inflated(codecs: object, parts: list[memoryview], out: memoryview) -> memoryview | None:
    """The zlib stream of ``parts`` inflated with libdeflate into ``out``; None unless it fills exactly ``out``."""
    stream = parts[0] if len(parts) == 1 else _joined("stream", parts)
    try:
        rows = codecs.deflate_decode(stream, out=out)  # type: ignore[attr-defined]
    except Exception:  # damaged or not of this size: libpng reports it from the original bytes
        return None
    return rows if len(rows) == len(out) else None


def _joined(name: str, parts: list[memoryview]) -> memoryview:
    out = _scratch(name, sum(len(p) for p in parts))
    _put(out, 0, parts)
    return out


def _put(buf: memoryview, at: int, pieces: list[memoryview]) -> int:
    """Copy ``pieces`` into ``buf`` from ``at``; where they end."""
    for piece in pieces:
        buf[at : at + len(piece)] = piece
        at += len(piece)
    return at
