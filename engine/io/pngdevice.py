"""A stack of plain grayscale PNG slices decoded half on the host, half on a CUDA device.

Decoding a PNG is two steps: inflating its zlib stream, then undoing the per-row filters (None, Sub, Up, Average,
Paeth: each byte predicted from its left, upper and upper-left neighbours). libpng does both on the host; on a
476 x 1024 x 1024 stack that is about 11 CPU-seconds per job, the largest host cost of a GPU worker's job and the
part that slows most when two workers share a host (issue 29). Here the host only inflates each slice, with
libdeflate (``imagecodecs.deflate_decode``, no GIL held, about 40 % of libpng's time), into one buffer of filtered
rows (the worker's page-locked buffer, ``engine.staging``, where it can have it); the device undoes the filters,
one thread per slice walking its rows in order (every filter type, bit-exact), joins the bytes of 16-bit samples
(big-endian in PNG) and the result is copied into the volume on the host.

Only slices that are plain 8- or 16-bit grayscale (colour type 0, no transparency), not interlaced, with every
IDAT chunk in one run and the first slice's size go this way; any other slice, a stream that does not inflate to
exactly its rows, or a row with an unknown filter type, is left for the host decoder (``engine.io.stack``), which
decodes it (or raises its error) as without this module.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from engine.io.parallel import ordered_map

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
CHUNK_BYTES = 1 << 30  # filtered bytes per device pass (Warp's arrays index with 32-bit integers)
MIN_DEVICE_BYTES = 1 << 30  # below this device budget the host decodes (a pass holds about 3x its chunk)


def plain_png_layout(data: bytes) -> tuple[int, int, int, bytes] | None:
    """``(width, height, bit depth, zlib stream)`` of a plain 8/16-bit grayscale, non-interlaced PNG; None for any
    other PNG (or bytes that are not a well-formed one)."""
    if len(data) < 45 or data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        return None
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if colour != 0 or depth not in (8, 16) or compression or filtering or interlace or not width or not height:
        return None
    parts: list[bytes] = []
    pos, ended = 8, False
    while pos + 12 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if len(body) != length:
            return None
        if kind == b"IDAT":
            if ended:
                return None  # IDAT chunks must be consecutive
            parts.append(body)
        elif parts:
            ended = True
        if kind == b"tRNS":
            return None
        if kind == b"IEND":
            break
        pos += 12 + length
    return (width, height, depth, b"".join(parts)) if parts else None


def unfilter_on_device(
    read: Callable[[int], bytes],
    out: np.ndarray,
    device: Any,
    threads: int,
    on_slice: Callable[[int], None] | None = None,
    chunk_bytes: int = CHUNK_BYTES,
) -> list[int]:
    """Decode the slices ``read(k)`` (k = 0..n-1) into ``out`` ((n, h, w) uint8 or uint16, C-contiguous) through
    ``device``; returns the indices it did not decode (the host decodes those). ``on_slice(k)`` is called as each
    slice is inflated (progress)."""
    import imagecodecs
    import warp as wp

    from engine.io.kernels import png as png_kernels
    from engine.staging import host_copies

    n, h, w = out.shape
    bpp = out.dtype.itemsize
    row = 1 + w * bpp
    per = h * row
    per_chunk = max(1, chunk_bytes // per)
    starts = list(range(0, n, per_chunk))
    sizes = [min(per_chunk, n - s) * per for s in starts]
    dev = wp.get_device(device)
    good = np.zeros(n, dtype=bool)
    with host_copies(dev, sum(-(-s // 256) * 256 for s in sizes)) as staging:
        bufs = [staging.empty((s,), wp.uint8) for s in sizes]

        def inflate(k: int) -> bool:
            layout = plain_png_layout(read(k))
            if layout is None or layout[:3] != (w, h, 8 * bpp):
                return False
            c, i = divmod(k, per_chunk)
            dest = bufs[c][1][i * per : (i + 1) * per]
            try:
                got = imagecodecs.deflate_decode(layout[3], out=dest)
            except Exception:  # a damaged stream: the host decoder reports it
                return False
            return bool(np.asarray(got).nbytes == per)

        for k, ok in enumerate(ordered_map(inflate, range(n), threads)):
            good[k] = ok
            if on_slice is not None:
                on_slice(k)
        if not good.any():
            return list(range(n))
        flat = out.reshape(n, h * w)
        bad = np.zeros(n, dtype=bool)
        for start, (raw_host, _) in zip(starts, bufs, strict=True):
            m = raw_host.shape[0] // per
            raw = wp.empty(raw_host.shape[0], dtype=wp.uint8, device=dev)
            wp.copy(raw, raw_host)
            rows = wp.empty(m * h * w * bpp, dtype=wp.uint8, device=dev)
            flags = wp.zeros(m, dtype=wp.int32, device=dev)
            wp.launch(png_kernels.unfilter_rows, dim=m, inputs=[raw, rows, flags, h, w * bpp, bpp], device=dev)
            del raw
            samples = rows
            if bpp == 2:
                samples = wp.empty(m * h * w, dtype=wp.uint16, device=dev)
                wp.launch(png_kernels.join_big_endian16, dim=m * h * w, inputs=[rows, samples], device=dev)
            target = wp.array(flat[start : start + m].reshape(-1), dtype=samples.dtype, device="cpu", copy=False)
            wp.copy(target, samples)
            bad[start : start + m] = flags.numpy() != 0
        wp.synchronize_device(dev)
    return [k for k in range(n) if not good[k] or bad[k]]


def wanted(device: Any, max_device_bytes: int | None) -> bool:
    """Whether a worker on ``device`` (a spec or Warp device) within ``max_device_bytes`` unfilters PNG slices on it:
    a CUDA device, and a budget (if any) of at least ``MIN_DEVICE_BYTES``."""
    if max_device_bytes is not None and max_device_bytes < MIN_DEVICE_BYTES:
        return False
    return str(device).startswith("cuda")

