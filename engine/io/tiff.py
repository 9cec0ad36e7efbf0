"""Multi-page TIFF and BigTIFF volumes read page by page into one preallocated (z, y, x) array.

A volume file of 50-200 GB cannot be read into bytes and then decoded into a second array of the same size. So a
multi-page TIFF (classic or BigTIFF, as tifffile, ImageJ, Fiji or a scanner's software write them) whose pages are
all grayscale of one shape and sample type (one of the engine's: uint8, uint16, int16, float32) is opened by
tifffile where its bytes lie, without reading them first: the file itself, an uncompressed tar's member, or a zip
member stored without compression (at its offset in the archive); a compressed archive member is read into memory
first (there is no other way to seek in it). Each page is then decoded straight into its plane of the array that
``allocate`` made (``page.asarray(out=...)``), on ``threads`` threads (tifffile's decoders release the GIL; the
file's reads are serialised by its lock); an ImageJ hyperstack over 4 GB, whose frames have no page of their own, is
read by tifffile into the same array (``asarray(out=...)``). The peak is the volume plus a few pages. Anything else
(colour, several series or shapes, other sample types) is decoded whole as before (``engine.io.stack``).
"""

from __future__ import annotations

import contextlib
import io
import struct
import zipfile
from collections.abc import Callable, Generator, Iterator
from typing import Any, cast

import numpy as np

from engine.errors import InputError
from engine.io.archive import InputLimits, Member
from engine.io.parallel import ordered_map

__all__ = ["read_tiff_volume"]

_NATIVE = (np.uint8, np.uint16, np.int16, np.float32)


def _in_place(m: Member) -> tuple[str, int, int] | None:
    """(file, offset, size) where the member's bytes lie unchanged in a file: a file of its own, an uncompressed
    tar's member, a zip member stored without compression; None otherwise (read into memory)."""
    if m._path is not None:
        return str(m._path), 0, m.size
    where = m.where
    if where is None:
        return None
    if where.kind == "file":
        return where.path, 0, where.size
    if where.kind == "tar":
        return where.path, where.offset, where.size
    if where.kind != "zip":
        return None
    try:
        with zipfile.ZipFile(where.path) as zf:
            info = zf.infolist()[where.index]
            if info.filename != where.name or info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:
                return None
            with open(where.path, "rb") as fh:  # the local header: its name and extra field lengths
                fh.seek(info.header_offset)
                head = fh.read(30)
    except (OSError, IndexError, zipfile.BadZipFile):
        return None
    if len(head) != 30 or head[:4] != b"PK\x03\x04":
        return None
    name_len, extra_len = struct.unpack("<HH", head[26:30])
    return where.path, info.header_offset + 30 + name_len + extra_len, info.file_size


@contextlib.contextmanager
def _opened(m: Member) -> Iterator[Any]:
    """The member as a ``tifffile.TiffFile``: where its bytes lie, else from memory."""
    import tifffile

    place = _in_place(m)
    try:
        if place is not None:
            path, offset, size = place
            tf = tifffile.TiffFile(path, offset=offset, size=size, name=m.name)
        else:
            tf = tifffile.TiffFile(io.BytesIO(m.read()), name=m.name)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot decode {m.name} as TIFF: {exc}") from None
    with tf:
        yield tf


def _page_stack(tf: Any) -> tuple[tuple[int, int, int], np.dtype[Any], list[Any] | None] | None:
    """The (z, y, x) shape, sample type and pages (None: frames without pages of their own) of a TIFF whose first
    series is a stack of grayscale planes of a type the engine meshes; None for anything else."""
    if not tf.series:
        return None
    series = tf.series[0]
    shape = tuple(int(n) for n in series.shape)
    dtype = np.dtype(series.dtype)
    first = tf.pages[0]
    if len(shape) < 2 or dtype.type not in _NATIVE or int(first.samplesperpixel) != 1:
        return None
    if sum(1 for n in shape[:-2] if n > 1) > 1:  # a hyperstack (channels or time points and z): decoded whole
        return None
    planes = int(np.prod(shape[:-2], dtype=np.int64))
    stack = (planes, shape[-2], shape[-1])
    pages = list(series.pages)
    if len(pages) == planes and all(
        p is not None and tuple(p.shape) == stack[1:] and np.dtype(p.dtype) == dtype for p in pages
    ):
        return stack, dtype, pages
    return stack, dtype, None


def read_tiff_volume(
    m: Member,
    label: str,
    limits: InputLimits,
    make: Callable[[tuple[int, ...], np.dtype[Any]], np.ndarray],
    geometry: Callable[[Any, Any], dict[str, Any]],
    on_progress: Callable[[float], None] | None = None,
    threads: int = 1,
) -> tuple[np.ndarray, dict[str, Any]] | None:
    """A multi-page TIFF / BigTIFF member as a (z, y, x) array decoded page by page into ``make(shape, dtype)`` (an
    uninitialised C-contiguous array), with its geometry hints ``geometry(tiff_file, first_page)`` (the stack
    loader's reading of the TIFF tags); None where it is not a stack of grayscale pages of one shape and engine type
    (the caller decodes it whole). ``on_progress`` gets the fraction of pages decoded.

    Raises:
        InputError: not a readable TIFF, a page that cannot be decoded, or more voxels than ``limits`` allow.
    """
    with _opened(m) as tf:
        found = _page_stack(tf)
        if found is None:
            return None
        shape, dtype, pages = found
        limits.check_voxels(shape, label)
        geo = geometry(tf, tf.pages[0])
        out = make(shape, dtype)
        try:
            if pages is None:  # frames without pages of their own (an ImageJ hyperstack over 4 GB): tifffile reads
                tf.asarray(series=0, out=out.reshape(tuple(tf.series[0].shape)), maxworkers=threads)
            else:
                _decode_pages(tf, pages, out, on_progress, threads)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"cannot decode {m.name} as TIFF: {exc}") from None
    if on_progress is not None:
        on_progress(1.0)
    return out, geo


def _decode_pages(
    tf: Any, pages: list[Any], out: np.ndarray, on_progress: Callable[[float], None] | None, threads: int
) -> None:
    """Each page decoded into its plane of ``out`` on ``threads`` threads (the file's reads under its lock)."""
    threads = max(1, min(threads, len(pages)))
    if threads > 1:
        tf.filehandle.set_lock(True)

    def decode(k: int) -> None:
        plane = out[k]
        got = pages[k].asarray(out=plane, maxworkers=1)
        if got is not plane and got.shape == plane.shape:
            plane[...] = got

    n = len(pages)
    step = max(1, n // 100)
    with contextlib.closing(cast(Generator[None, None, None], ordered_map(decode, range(n), threads))) as done:
        for k, _ in enumerate(done, start=1):
            if on_progress is not None and k % step == 0:
                on_progress(k / n)
