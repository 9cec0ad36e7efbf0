"""PNG row filters undone on the device (``engine.io.pngdevice``)."""

from __future__ import annotations

import warp as wp


@wp.func
def paeth(a: int, b: int, c: int) -> int:
    """The PNG Paeth predictor: whichever of left, up, upper-left is nearest to left + up - upper-left."""
    p = a + b - c
    pa = wp.abs(p - a)
    pb = wp.abs(p - b)
    pc = wp.abs(p - c)
    if pa <= pb and pa <= pc:
        return a
    if pb <= pc:
        return b
    return c


@wp.kernel
def unfilter_rows(
    raw: wp.array(dtype=wp.uint8),
    out: wp.array(dtype=wp.uint8),
    bad: wp.array(dtype=wp.int32),
    height: int,
    rowbytes: int,
    bpp: int,
):
    """One slice per thread: ``raw`` holds each slice's ``height`` rows of 1 filter byte + ``rowbytes`` bytes;
    ``out`` gets the unfiltered rows (PNG byte order). A filter type above 4 sets ``bad[slice]``."""
    z = wp.tid()
    src = z * height * (rowbytes + 1)
    dst = z * height * rowbytes
    for r in range(height):
        kind = int(raw[src])
        if kind > 4:
            bad[z] = 1
        for i in range(rowbytes):
            x = int(raw[src + 1 + i])
            a = int(0)
            b = int(0)
            c = int(0)
            if i >= bpp:
                a = int(out[dst + i - bpp])
            if r > 0:
                b = int(out[dst - rowbytes + i])
                if i >= bpp:
                    c = int(out[dst - rowbytes + i - bpp])
            v = x
            if kind == 1:
                v = x + a
            elif kind == 2:
                v = x + b
            elif kind == 3:
                v = x + (a + b) // 2
            elif kind == 4:
                v = x + paeth(a, b, c)
            out[dst + i] = wp.uint8(v & 255)
        src = src + rowbytes + 1
        dst = dst + rowbytes


@wp.kernel
def join_big_endian16(rows: wp.array(dtype=wp.uint8), samples: wp.array(dtype=wp.uint16)):
    """16-bit samples from their big-endian byte pairs."""
    k = wp.tid()
    samples[k] = wp.uint16((int(rows[2 * k]) << 8) | int(rows[2 * k + 1]))
