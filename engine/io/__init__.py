"""Loaders: slice stacks, volume files and DICOM series -> :class:`engine.types.Volume`.

``load_volume`` accepts a zip / tar / tar.gz archive or a folder of 2-D slices (PNG, TIFF, JPEG, BMP) or of DICOM
files, a multi-page TIFF or BigTIFF (read page by page, ``engine.io.tiff``), a ``.npy`` (z, y, x) array, a single
DICOM file, or an OME-Zarr image (v0.4 / v0.5: a folder, a zip of one, or ``s3://bucket/key``; read chunk by chunk,
``engine.io.omezarr``). DICOM is recognised by content (with or without preamble and file extension); Zarr by its
metadata files; everything else by its file signature.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from engine.errors import InputError, NotAScanError
from engine.io.archive import InputLimits, open_members
from engine.io.dicom import has_dicom_images, load_dicom
from engine.io.omezarr import ZarrSource, is_remote, load_ome_zarr, zarr_in
from engine.io.parallel import decode_threads
from engine.io.png_rows import DeviceRows
from engine.io.stack import Allocate, StackWarning, check_spacing, load_stack, natural_key
from engine.types import Volume

__all__ = [
    "InputLimits",
    "InputSummary",
    "StackWarning",
    "decode_threads",
    "inspect_input",
    "load_volume",
    "natural_key",
]


@dataclass(frozen=True)
class InputSummary:
    """What a quick look at an input found: container kind, files, image slices and DICOM files."""

    kind: str
    files: int
    images: int
    dicom: int


def inspect_input(path: str | Path, limits: InputLimits | None = None) -> InputSummary:
    """A quick check of an upload before it is queued: the container opens, its member names are safe, its member
    count and declared sizes and ratios are within ``limits``, and it holds image slices or DICOM files (by their
    first bytes). Loading checks the rest (actual bytes, slice shapes, spacing).

    Raises:
        InputError: not a readable archive or volume file, unsafe or too large, or nothing to build from.
    """
    from engine.io.dicom import looks_like_dicom
    from engine.io.stack import image_kind

    label = Path(path).name or str(path)
    if is_remote(path):
        return InputSummary("ome-zarr (s3)", 0, 0, 0)  # opened when loaded: the store is named if unreachable
    with open_members(path, limits, heads_only=True) as members:
        if (found := zarr_in(members, Path(path))) is not None:
            return InputSummary(f"ome-zarr ({found.kind})", len(members.members) + len(members.ignored), 0, 0)
        images = sum(1 for m in members.members if image_kind(m.head))
        dicom = sum(1 for m in members.members if looks_like_dicom(m.head))
        summary = InputSummary(members.kind, len(members.members), images, dicom)
        flat = summary.kind == "file" and image_kind(members.members[0].head) in ("png", "jpeg", "bmp")
    if summary.kind == "file" and not (images or dicom):
        raise NotAScanError(
            f"{label} is neither an archive (zip, tar, tar.gz) nor a volume file (.npy, TIFF, DICOM) that "
            "bonemesh reads"
        )
    if flat:
        raise NotAScanError(f"{label} is a single 2-D image, not a scan: send all the slices in one zip or tar archive")
    if not (images or dicom):
        raise InputError(
            f"{label} holds {summary.files} file(s) but no image slices (PNG, TIFF, JPEG, BMP, .npy) and no DICOM files"
        )
    return summary


def load_volume(
    path: str | Path,
    *,
    spacing_zyx_mm: Sequence[float] | None = None,
    series_uid: str | None = None,
    limits: InputLimits | None = None,
    on_progress: Callable[[float], None] | None = None,
    threads: int | None = None,
    processes: bool | None = None,
    allocate: Allocate | None = None,
    rows: DeviceRows | None = None,
    level: int | str | None = None,
) -> Volume:
    """Load a scan as a (z, y, x) :class:`Volume`.

    Args:
        path: archive (zip, tar, tar.gz/bz2/xz), folder, multi-page TIFF, ``.npy`` or DICOM file, or an OME-Zarr
            image: a folder (``scan.ome.zarr``, or one level's array ``scan.ome.zarr/2``), a zip of one, or
            ``s3://bucket/key`` (``engine.io.omezarr.s3_store``: the S3 settings from the environment).
        spacing_zyx_mm: voxel size (z, y, x) in mm. Required for image stacks and ``.npy`` unless TIFF tags carry
            it, and for OME-Zarr without length units (where given, it wins over the metadata); for DICOM it may
            only fill in what the headers lack (a conflicting value is an error).
        series_uid: the DICOM SeriesInstanceUID to load when the input holds several (default: the largest).
        limits: safety limits on archive members, sizes, compression ratio and voxel count.
        on_progress: called with the fraction (0..1) of the files read, as slices are decoded.
        threads: threads that read and decode slices side by side (default: the CPUs this process may run on,
            ``engine.io.parallel.decode_threads``); 1 decodes on the calling thread. The result does not depend
            on it.
        processes: DICOM only: parse and decode the files in ``threads`` worker processes instead of threads
            (pydicom holds the GIL; ``engine.io.procs``). None (default): for inputs of at least
            ``engine.io.dicom.PROCESS_MIN_FILES`` DICOM files and ``threads`` >= ``PROCESS_MIN_WORKERS``, where this
            process may start processes; False: threads. The result does not depend on it.
        allocate: image stacks only: makes the array the slices are decoded into, ``allocate(shape, dtype)`` -> an
            uninitialised C-contiguous array (default ``np.empty``; a worker passes its reused page-locked buffer,
            ``engine.staging.pinned_volumes``). DICOM series make their own.
        rows: image stacks only: a GPU's ``engine.io.png_rows.DeviceRows`` (``device_rows``): plain grayscale PNG
            slices are then inflated on the host and unfiltered on that device. The result does not depend on it.
        level: OME-Zarr only: the resolution level, by index (0, the default: full resolution) or path.

    Returns:
        The volume: integer data stay integer (uint8/uint16/int16); DICOM CT is in HU (int16 where exact,
        else float32), resampled onto a regular orthogonal grid when gaps are uneven or the gantry was tilted.

    Raises:
        InputError: unreadable or unsafe input, missing voxel size, inconsistent slices or series.
        ValueError: ``threads`` is not a positive integer.
    """
    spacing = check_spacing(spacing_zyx_mm)
    threads = decode_threads(threads)
    limits = limits or InputLimits()
    label = Path(path).name or str(path)
    zarr = partial(load_ome_zarr, level=level, spacing_zyx_mm=spacing, limits=limits, on_progress=on_progress,
                   allocate=allocate)  # fmt: skip
    if is_remote(path):
        return zarr(ZarrSource("s3", str(path)))
    with open_members(path, limits) as members:
        if (zarr_src := zarr_in(members, Path(path))) is not None:
            return zarr(zarr_src)
        if level is not None:
            raise InputError(f"level={level!r} was given, but {label} is not an OME-Zarr image")
        if has_dicom_images(members):
            vol = load_dicom(
                members,
                label,
                spacing_zyx_mm=spacing,
                series_uid=series_uid,
                limits=limits,
                on_progress=on_progress,
                threads=threads,
                processes=processes,
            )
            if vol is not None:
                vol.source["container"] = members.kind
                return vol
        if series_uid is not None:
            raise InputError(f"series_uid={series_uid!r} was given, but {label} holds no DICOM images")
        return load_stack(
            members, label, spacing, limits, on_progress=on_progress, threads=threads, allocate=allocate, rows=rows
        )
