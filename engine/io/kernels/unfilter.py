"""The Warp kernel that turns PNG slices' inflated rows into samples on the device; ``unfilter.cl`` is the OpenCL C
version, the same arithmetic.

``rows`` holds slice ``s``'s rows from byte ``s * plane``: each row is its filter-type byte, then ``width * bpp``
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


CHUNK = 32  # samples a thread loads before it reconstructs them: one memory latency per chunk, not per byte
wp.set_module_options({"max_unroll": CHUNK})
_chunk = wp.types.vector(length=CHUNK, dtype=wp.int32)


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
):
    """Reconstruct byte lane ``i % bpp`` of slice ``s = slices[i // bpp]`` (its rows at ``s * plane``), row after row
    (each row needs the one above), into the slice's samples in native (little-endian) order: byte
    ``(s * height + y) * width * bpp + x * bpp + bpp - 1 - lane`` of ``out``. ``CHUNK`` samples' filtered bytes and
    the bytes above them are loaded before any is reconstructed (the loads do not wait on each other). A filter type
    above 4 sets ``bad[s]`` and stops."""
    i = wp.tid()
    s = slices[i // bpp]
    lane = i % bpp
    line = width * bpp
    swapped = bpp - 1 - lane
    for y in range(height):
        src = s * plane + y * (1 + line)
        dst = (s * height + y) * line + swapped
        kind = int(rows[src])
        if kind > 4:
            bad[s] = 1
            return
        src = src + 1 + lane
        a = int(0)
        c = int(0)
        for x0 in range(0, width, CHUNK):
            raw = _chunk()
            up = _chunk()
            for j in range(CHUNK):
                x = x0 + j
                if x < width:
                    raw[j] = int(rows[src + x * bpp])
                    if y > 0:
                        up[j] = int(out[dst - line + x * bpp])
            for j in range(CHUNK):
                x = x0 + j
                if x < width:
                    b = up[j]
                    v = _reconstruct(kind, raw[j], a, b, c)
                    out[dst + x * bpp] = wp.uint8(v)
                    a = v
                    c = b
