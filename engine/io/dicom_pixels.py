"""Reading DICOM files and decoding a series' pixels into one (z, y, x) array on a pool of threads or processes.

The parse (pydicom) is Python and holds the GIL; reading the member (zip inflate) and the decoders of compressed
transfer syntaxes (pylibjpeg's OpenJPEG / libjpeg, pydicom's RLE) and the rescale to HU are where threads overlap.
With a :class:`~engine.io.procs.DecodePool` the slices are decoded in its processes instead, straight into the
shared volume; the result is the same.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import math
import warnings
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from engine.errors import InputError
from engine.io.archive import Member
from engine.io.parallel import ordered_map
from engine.io.readers import Where

if TYPE_CHECKING:
    from engine.io.procs import DecodePool

_Stats = tuple[tuple[int, ...], np.dtype[Any], float, float]  # a decoded slice's shape, dtype, min and max


class SliceLike(Protocol):
    """What decoding needs of a scanned slice (``engine.io.dicom._Slice``)."""

    member: Member
    rows: int
    cols: int
    header: dict[str, Any]


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Silence pydicom's complaints about odd values in legacy headers while files are parsed and decoded.

    Entered on the loader's own thread around a whole pass, never inside the pool's threads: the warnings filters
    are process-wide, and ``catch_warnings`` entered and left by several threads at once can leave one thread's
    filter in place for good.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def read_dataset(member: Member, *, pixels: bool) -> Any | None:
    """Parse a member as DICOM; None when it is not one. Call it inside :func:`quiet`."""
    import pydicom
    from pydicom.uid import ExplicitVRBigEndian, ExplicitVRLittleEndian, ImplicitVRLittleEndian

    try:
        ds = pydicom.dcmread(io.BytesIO(member.read()), force=True, stop_before_pixels=not pixels)
        if "TransferSyntaxUID" not in ds.file_meta:  # raw data set: say how it was encoded
            implicit, little = ds.original_encoding
            ds.file_meta.TransferSyntaxUID = (
                ImplicitVRLittleEndian if implicit else ExplicitVRLittleEndian if little else ExplicitVRBigEndian
            )
    except Exception:
        return None
    return ds


def decode_pixels(member: Member, transfer_syntax: str) -> np.ndarray:
    """One slice's stored pixel values (call inside :func:`quiet`).

    Raises:
        InputError: the pixel data cannot be decoded.
    """
    ds = read_dataset(member, pixels=True)
    try:
        return ds.pixel_array  # type: ignore[union-attr,no-any-return]
    except Exception as exc:
        raise InputError(f"cannot decode the pixels of {member.name} ({transfer_syntax}): {exc}") from None


def _store(raw: np.ndarray, k: int, arr: np.ndarray) -> _Stats:
    """Put a decoded slice into plane ``k`` when it fits; what the caller checks and the rescale needs."""
    if arr.shape == raw.shape[1:] and arr.dtype == raw.dtype:
        raw[k] = arr
    return arr.shape, arr.dtype, float(arr.min()), float(arr.max())


def decode_into_shared(job: tuple[int, Where, bytes, str, tuple[int, ...], str]) -> _Stats:
    """In a decode process: decode one slice into plane ``k`` of the pool's shared volume."""
    from engine.io.procs import worker_array

    k, where, head, syntax, shape, dtype = job
    member = Member.at(where, head)
    return _store(worker_array(shape, dtype), k, decode_pixels(member, syntax))


def series_pixels(
    series: Sequence[SliceLike], threads: int = 1, procs: DecodePool | None = None
) -> tuple[np.ndarray, str, float]:
    """Decode the pixel data into one (z, y, x) array, rescaled to HU (CT) where the headers say so.

    Slices after the first are decoded on ``threads`` threads (or in the processes of ``procs``, into its shared
    volume) straight into their planes; a failure is raised for the first failing slice in slice order, as a serial
    loop would. The rescale runs in place, slice by slice.

    Returns:
        The array (uint8/uint16/int16 where exact, else float32), its units ("HU" for CT, else "raw") and the
        lowest rescaled value (the fill for resampling).

    Raises:
        InputError: undecodable pixels, or a slice whose decoded shape or dtype differs from the first's.
    """
    slopes = np.array([s.header["slope"] for s in series])
    inters = np.array([s.header["intercept"] for s in series])
    is_ct = series[0].header["modality"].upper() == "CT"
    with quiet():
        first = decode_pixels(series[0].member, series[0].header["transfer_syntax"])
        shape = (len(series), series[0].rows, series[0].cols)
        raw = np.empty(shape, dtype=first.dtype) if procs is None else procs.shared_array(shape, first.dtype)

        def decode_into(k: int) -> _Stats:
            return _store(raw, k, decode_pixels(series[k].member, series[k].header["transfer_syntax"]))

        if procs is None:
            rest = ordered_map(decode_into, range(1, len(series)), threads)
        else:
            jobs = [_job(k, s, shape, first.dtype) for k, s in enumerate(series) if k]
            rest = ordered_map(decode_into_shared, jobs, procs.workers, procs.pool, procs.chunk(len(jobs)))
        first_stats = _store(raw, 0, first)
        del first
        lo, hi = math.inf, -math.inf
        with contextlib.closing(rest):  # no pool thread outlives the call, also when the loop raises
            for k, (shape, dtype, amin, amax) in enumerate(itertools.chain([first_stats], rest)):
                if shape != raw.shape[1:] or dtype != raw.dtype:
                    raise InputError(
                        f"expected {raw.shape[1:]} {raw.dtype} pixels in {series[k].member.name}, got {shape} {dtype}"
                    )
                lo = min(lo, amin * slopes[k] + inters[k], amax * slopes[k] + inters[k])
                hi = max(hi, amin * slopes[k] + inters[k], amax * slopes[k] + inters[k])
    units = "HU" if is_ct else "raw"
    if np.all(slopes == 1) and np.all(inters == 0):
        return narrow_raw(raw), units, float(raw.min())
    integral = np.all(slopes == np.round(slopes)) and np.all(inters == np.round(inters))
    if integral and -32768 <= lo and hi <= 32767:
        out = raw.view(np.int16) if raw.dtype.itemsize == 2 else np.empty(raw.shape, np.int16)

        def rescale16(k: int) -> None:  # in place, slice by slice: no full-size temporary
            out[k] = (raw[k].astype(np.int32) * int(slopes[k]) + int(inters[k])).astype(np.int16)

        for _ in ordered_map(rescale16, range(len(series)), threads):
            pass
        return out, units, lo
    out32 = np.empty(raw.shape, np.float32)

    def rescale32(k: int) -> None:
        out32[k] = raw[k].astype(np.float32) * np.float32(slopes[k]) + np.float32(inters[k])

    for _ in ordered_map(rescale32, range(len(series)), threads):
        pass
    return out32, units, lo


def _job(
    k: int, s: SliceLike, shape: tuple[int, ...], dtype: np.dtype[Any]
) -> tuple[int, Where, bytes, str, tuple[int, ...], str]:
    if s.member.where is None:
        raise RuntimeError(f"{s.member.name} cannot be read from another process")
    return k, s.member.where, s.member.head, s.header["transfer_syntax"], shape, dtype.str


def narrow_raw(raw: np.ndarray) -> np.ndarray:
    """Stored values in the narrowest dtype the engine uses that holds them all."""
    if raw.dtype in (np.uint8, np.uint16, np.int16, np.float32):
        return raw
    if raw.dtype.kind not in "iu":
        return raw.astype(np.float32)
    lo, hi = int(raw.min()), int(raw.max())
    for dt in (np.uint16, np.int16):
        if np.iinfo(dt).min <= lo and hi <= np.iinfo(dt).max:
            return raw.astype(dt)
    return raw.astype(np.float32)
