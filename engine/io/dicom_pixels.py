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
from engine.io.dicom_frames import frame_label
from engine.io.parallel import ordered_map
from engine.io.readers import Where

if TYPE_CHECKING:
    from engine.io.procs import DecodePool

_Stats = tuple[tuple[int, ...], np.dtype[Any], float, float]  # a decoded slice's shape, dtype, min and max


class SliceLike(Protocol):
    """What decoding needs of a scanned slice (``engine.io.dicom._Slice``): a frame of a multi-frame image has
    ``frame`` (from 0) and its ``file``; ``member`` names the frame."""

    member: Member
    rows: int
    cols: int
    header: dict[str, Any]
    frame: int | None
    file: Member | None


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


def decode_frame(ds: Any, index: int, label: str, transfer_syntax: str) -> np.ndarray:
    """Frame ``index`` (from 0) of a parsed multi-frame data set, alone (call inside :func:`quiet`).

    Raises:
        InputError: the frame cannot be decoded (``label`` names it).
    """
    from pydicom.pixels import pixel_array

    try:
        return pixel_array(ds, index=index)
    except Exception as exc:
        raise InputError(f"cannot decode the pixels of {label} ({transfer_syntax}): {exc}") from None


def iter_frames(ds: Any, name: str, transfer_syntax: str) -> Iterator[tuple[int, np.ndarray]]:
    """(index, pixels) of every frame of a parsed multi-frame data set, in the file's order, each decoded once: an
    encapsulated (compressed) one is walked through once, not searched for each frame (call inside :func:`quiet`).

    Raises:
        InputError: a frame cannot be decoded (the message names it), or the data set is None (unreadable).
    """
    from pydicom.pixels import as_pixel_options, get_decoder

    index = 0  # the frame being decoded, for the message
    try:
        decoder = get_decoder(ds.file_meta.TransferSyntaxUID)
        for arr, _ in decoder.iter_array(ds, validate=True, **as_pixel_options(ds)):
            yield index, arr
            index += 1
    except Exception as exc:
        where = frame_label(name, index) if ds is not None else name
        raise InputError(f"cannot decode the pixels of {where} ({transfer_syntax}): {exc}") from None


def _store(raw: np.ndarray, k: int, arr: np.ndarray) -> _Stats:
    """Put a decoded slice into plane ``k`` when it fits; what the caller checks and the rescale needs."""
    if arr.shape == raw.shape[1:] and arr.dtype == raw.dtype:
        raw[k] = arr
    return arr.shape, arr.dtype, float(arr.min()), float(arr.max())


_Planes = tuple[tuple[int, int | None], ...]  # (plane k, frame index or None for a single-frame file) of one file


def _decode_file(
    raw: np.ndarray, member: Member, syntax: str, planes: _Planes, ds: Any | None = None
) -> list[tuple[int, _Stats]]:
    """Decode one file's slices into their planes of ``raw``: a single-frame file's one, or the frames of a
    multi-frame file (``ds``: the file already parsed), each decoded once, in the file's order.

    Raises:
        InputError: a slice cannot be decoded, or the pixel data end before a frame wanted.
    """
    if len(planes) == 1 and planes[0][1] is None:
        k = planes[0][0]
        return [(k, _store(raw, k, decode_pixels(member, syntax)))]
    wanted = {frame: k for k, frame in planes}
    done = []
    if ds is None:
        ds = read_dataset(member, pixels=True)
    for index, arr in iter_frames(ds, member.name, syntax):
        if index in wanted:
            k = wanted.pop(index)
            done.append((k, _store(raw, k, arr)))
        if not wanted:
            break
    if wanted:
        first = frame_label(member.name, min(f for f in wanted if f is not None))
        raise InputError(f"cannot decode the pixels of {first} ({syntax}): the pixel data end before it")
    return done


def decode_file_into_shared(job: tuple[_Planes, Where, bytes, str, tuple[int, ...], str]) -> list[tuple[int, _Stats]]:
    """In a decode process: decode one file's slices into their planes of the pool's shared volume."""
    from engine.io.procs import worker_array

    planes, where, head, syntax, shape, dtype = job
    return _decode_file(worker_array(shape, dtype), Member.at(where, head), syntax, planes)


def _by_file(series: Sequence[SliceLike]) -> list[tuple[Member, str, _Planes]]:
    """The slices by the file they are read from (the frames of a multi-frame file together), in the order of each
    file's first slice: (file, transfer syntax, planes)."""
    files: dict[int, tuple[Member, str, list[tuple[int, int | None]]]] = {}
    for k, s in enumerate(series):
        member = s.member if s.file is None else s.file
        files.setdefault(id(member), (member, s.header["transfer_syntax"], []))[2].append((k, s.frame))
    return [(member, syntax, tuple(planes)) for member, syntax, planes in files.values()]


def series_pixels(
    series: Sequence[SliceLike], threads: int = 1, procs: DecodePool | None = None
) -> tuple[np.ndarray, str, float]:
    """Decode the pixel data into one (z, y, x) array, rescaled to HU (CT) where the headers say so.

    The first slice is decoded alone (it gives the array's dtype); then each file (a single-frame image, or all the
    wanted frames of a multi-frame one, decoded once) on ``threads`` threads, or in the processes of ``procs``,
    into its shared volume, straight into the planes. A failure is raised for the first failing file in the order
    of the files' first slices (for single-frame images: the first failing slice in slice order), as a serial loop
    would. The rescale (each slice's own slope and intercept) runs in place, slice by slice.

    Returns:
        The array (uint8/uint16/int16 where exact, else float32), its units ("HU" for CT, else "raw") and the
        lowest rescaled value (the fill for resampling).

    Raises:
        InputError: undecodable pixels, or a slice whose decoded shape or dtype differs from the first's.
    """
    slopes = np.array([s.header["slope"] for s in series])
    inters = np.array([s.header["intercept"] for s in series])
    is_ct = series[0].header["modality"].upper() == "CT"
    files = _by_file(series)
    with quiet():
        head, parsed = series[0], None
        if head.frame is None:
            first = decode_pixels(head.member, head.header["transfer_syntax"])
        else:  # one frame decoded alone; the file's other frames are decoded with it, once
            parsed = read_dataset(files[0][0], pixels=True)
            first = decode_frame(parsed, head.frame, head.member.name, head.header["transfer_syntax"])
        shape = (len(series), series[0].rows, series[0].cols)
        raw = np.empty(shape, dtype=first.dtype) if procs is None else procs.shared_array(shape, first.dtype)
        first_stats = _store(raw, 0, first)
        del first
        todo = [(m, syntax, tuple(p for p in planes if p[0] != 0)) for m, syntax, planes in files]
        todo = [job for job in todo if job[2]]
        if procs is None:
            cached = {id(files[0][0]): parsed}  # the first file is not parsed twice on threads
            del parsed

            def decode_into(job: tuple[Member, str, _Planes]) -> list[tuple[int, _Stats]]:
                return _decode_file(raw, *job, ds=cached.pop(id(job[0]), None))

            rest = ordered_map(decode_into, todo, threads)
        else:
            del parsed
            jobs = [_job(planes, m, syntax, shape, raw.dtype) for m, syntax, planes in todo]
            rest = ordered_map(decode_file_into_shared, jobs, procs.workers, procs.pool, procs.chunk(len(jobs)))
        lo, hi = math.inf, -math.inf
        with contextlib.closing(rest):  # no pool thread outlives the call, also when the loop raises
            stats = itertools.chain([(0, first_stats)], itertools.chain.from_iterable(rest))
            for k, (got, dtype, amin, amax) in stats:
                if got != raw.shape[1:] or dtype != raw.dtype:
                    raise InputError(
                        f"expected {raw.shape[1:]} {raw.dtype} pixels in {series[k].member.name}, got {got} {dtype}"
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
    planes: _Planes, member: Member, syntax: str, shape: tuple[int, ...], dtype: np.dtype[Any]
) -> tuple[_Planes, Where, bytes, str, tuple[int, ...], str]:
    if member.where is None:
        raise RuntimeError(f"{member.name} cannot be read from another process")
    return planes, member.where, member.head, syntax, shape, dtype.str


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
