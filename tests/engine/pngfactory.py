"""Grayscale PNGs built byte by byte for the decoder tests: any filter type per row, 8 or 16 bits, several IDAT
chunks, interlaced (Adam7); and slices of noise with smooth runs (what real filters meet)."""

from __future__ import annotations

import struct
import zlib

import numpy as np

ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def png_of_stream(img: np.ndarray, stream: bytes, idat_parts: int = 1, interlace: int = 0) -> bytes:
    """A grayscale PNG of ``img``'s size and depth around the zlib ``stream``, cut into ``idat_parts`` IDATs."""
    h, w = img.shape
    ihdr = struct.pack(">IIBBBBB", w, h, 8 * img.dtype.itemsize, 0, 0, 0, interlace)
    cut = np.linspace(0, len(stream), idat_parts + 1).astype(int)
    idats = b"".join(chunk(b"IDAT", stream[cut[i] : cut[i + 1]]) for i in range(idat_parts))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idats + chunk(b"IEND", b"")


def encode_png(img: np.ndarray, filters: np.ndarray, idat_parts: int = 1) -> bytes:
    """A grayscale PNG of ``img`` (uint8/uint16) with row ``r`` filtered by type ``filters[r]`` (0-4)."""
    h, w = img.shape
    bpp = img.dtype.itemsize
    raw = img.astype(img.dtype.newbyteorder(">")).view(np.uint8).reshape(h, w * bpp).astype(np.int64)
    rows = []
    for r in range(h):
        x = raw[r]
        a = np.concatenate([np.zeros(bpp, np.int64), x[:-bpp]])
        b = raw[r - 1] if r else np.zeros_like(x)
        c = np.concatenate([np.zeros(bpp, np.int64), b[:-bpp]])
        pred = [np.zeros_like(x), a, b, (a + b) // 2, _paeth(a, b, c)][int(filters[r])]
        rows.append(bytes([int(filters[r])]) + ((x - pred) % 256).astype(np.uint8).tobytes())
    return png_of_stream(img, zlib.compress(b"".join(rows), 6), idat_parts)


def encode_adam7(img: np.ndarray) -> bytes:
    """An interlaced (Adam7) grayscale PNG of ``img``, every row unfiltered."""
    big = img.astype(img.dtype.newbyteorder(">"))
    rows = []
    for x0, y0, dx, dy in ADAM7:
        sub = big[y0::dy, x0::dx]
        if sub.size:
            rows += [b"\x00" + r.tobytes() for r in sub]
    return png_of_stream(img, zlib.compress(b"".join(rows)), interlace=1)


def gray_slices(rng: np.random.Generator, n: int, shape: tuple[int, int], dtype: type) -> np.ndarray:
    """``n`` slices of ``shape``: running sums of small steps, one sample in ten replaced by noise."""
    top = np.iinfo(dtype).max
    smooth = np.cumsum(rng.integers(-3, 4, size=(n, *shape)), axis=2) % (top + 1)
    return np.where(rng.random((n, *shape)) < 0.1, rng.integers(0, top + 1, size=(n, *shape)), smooth).astype(dtype)
