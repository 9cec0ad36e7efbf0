"""The Warp kernel that turns PNG slices' inflated rows into samples on the device; ``unfilter.cl`` is the OpenCL C
version, the same arithmetic.

``rows`` holds slice ``s``'s rows from byte ``s * plane``: each row is its filter-type byte, then ``width * bpp``
filtered bytes (PNG's scanlines, ``bpp`` bytes a sample, big-endian). The filters (PNG spec, section 9) predict a
byte from the reconstructed bytes ``a`` (one sample to the left, same byte lane), ``b`` (above) and ``c`` (above
left): 0 none, 1 Sub (a), 2 Up (b), 3 Average ((a + b) // 2), 4 Paeth (whichever of a, b, c is nearest a + b - c).
"""

from __future__ import annotations

import warp as wp

from engine.io.kernels.steps import BAND, BLOCK


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
    out: wp.array(dtype=wp.uint8),
    bad: wp.array(dtype=wp.int32),
    height: int,
    width: int,
    bpp: int,
    step: int,
):
    """One step of a wavefront over every slice: thread ``i`` reconstructs byte lane ``lane`` of column block ``j``
    (samples ``j * BLOCK`` on) of slice ``s = slices[...]`` (its rows at ``s * plane``), in the band of ``BAND``
    rows ``(step - j) * BAND`` on, into the slice's samples in native (little-endian) order: byte
    ``(s * height + y) * width * bpp + x * bpp + bpp - 1 - lane`` of ``out``. What a block needs, the samples to
    its left and above, the earlier steps wrote: its left neighbour did this band one step before, and it did the
    band above itself. A filter type above 4 sets ``bad[s]`` (the row is then taken as unfiltered)."""
    i = wp.tid()
    blocks = (width + BLOCK - 1) // BLOCK
    j = i % blocks
    y0 = (step - j) * BAND
    if y0 < 0 or y0 >= height:
        return
    s = slices[i // blocks // bpp]
    lane = (i // blocks) % bpp
    line = width * bpp
    x0 = j * BLOCK
    x1 = wp.min(x0 + BLOCK, width)
    for y in range(y0, wp.min(y0 + BAND, height)):
        src = s * plane + y * (1 + line)
        dst = (s * height + y) * line + bpp - 1 - lane
        kind = int(rows[src])
        if kind > 4:
            bad[s] = 1
            kind = 0
        src = src + 1 + lane
        a = int(0)
        c = int(0)
        if x0 > 0:
            a = int(out[dst + (x0 - 1) * bpp])
            if y > 0:
                c = int(out[dst - line + (x0 - 1) * bpp])
        for x in range(x0, x1):
            b = int(0)
            if y > 0:
                b = int(out[dst - line + x * bpp])
            v = _reconstruct(kind, int(rows[src + x * bpp]), a, b, c)
            out[dst + x * bpp] = wp.uint8(v)
            a = v
            c = b
