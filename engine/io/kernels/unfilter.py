"""Warp kernels that turn PNG slices' inflated rows into samples on the device; ``unfilter.cl`` is the OpenCL C
version, the same arithmetic.

``rows`` holds one slice's rows per line of the 2-D array: each row is its filter-type byte, then ``width * bpp``
filtered bytes (PNG's scanlines, ``bpp`` bytes a sample, big-endian). The filters (PNG spec, section 9) predict a
byte from the reconstructed bytes ``a`` (one sample to the left, same byte lane), ``b`` (above) and ``c`` (above
left): 0 none, 1 Sub (a), 2 Up (b), 3 Average ((a + b) // 2), 4 Paeth (whichever of a, b, c is nearest a + b - c).
"""

from __future__ import annotations

import warp as wp


@wp.func
def _reconstruct(kind: int, raw: int, a: int, b: int, c: int) -> int:
    pred = int(0)
    if kind == 1:
        pred = a
    elif kind == 2:
        pred = b
    elif kind == 3:
        pred = (a + b) >> 1
    elif kind == 4:
        p = a + b - c
        pa = wp.abs(p - a)
        pb = wp.abs(p - b)
        pc = wp.abs(p - c)
        pred = c
        if pa <= pb and pa <= pc:
            pred = a
        elif pb <= pc:
            pred = b
    return (raw + pred) & 255


@wp.kernel
def unfilter_kernel(
    rows: wp.array(dtype=wp.uint8),
    plane: int,
    slices: wp.array(dtype=wp.int32),
    bad: wp.array(dtype=wp.int32),
    height: int,
    width: int,
    bpp: int,
):
    """Undo the row filters in place: thread ``i`` reconstructs byte lane ``i % bpp`` of slice ``slices[i // bpp]``
    (its rows at ``slices[i // bpp] * plane``), row after row (each row needs the one above); a filter type above 4
    sets ``bad[slice]`` and stops."""
    i = wp.tid()
    s = slices[i // bpp]
    lane = i % bpp
    stride = 1 + width * bpp
    for y in range(height):
        row = s * plane + y * stride
        kind = int(rows[row])
        if kind > 4:
            bad[s] = 1
            return
        a = int(0)
        c = int(0)
        for x in range(width):
            p = row + 1 + x * bpp + lane
            b = int(0)
            if y > 0:
                b = int(rows[p - stride])
            v = _reconstruct(kind, int(rows[p]), a, b, c)
            rows[p] = wp.uint8(v)
            a = v
            c = b


@wp.kernel
def pack_kernel(
    rows: wp.array(dtype=wp.uint8),
    plane: int,
    slices: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.uint8),
    height: int,
    width: int,
    bpp: int,
):
    """Samples from unfiltered rows: byte ``x`` of line ``y`` of slice ``s = slices[j]``, at
    ``(s * height + y) * width * bpp + x`` of ``out``, in native (little-endian) order: a 16-bit sample's big-endian
    pair swapped."""
    j, y, x = wp.tid()
    s = slices[j]
    line = width * bpp
    lane = bpp - 1 - x % bpp
    out[(s * height + y) * line + x] = rows[s * plane + y * (1 + line) + 1 + (x // bpp) * bpp + lane]
