"""Stacks of 2-D images (PNG, TIFF, JPEG, BMP), multi-page TIFFs and ``.npy`` arrays -> :class:`Volume`."""

from __future__ import annotations

import contextlib
import io
import math
import re
import warnings
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.errors import InputError, NoSpacingError
from engine.io.archive import InputLimits, Member, Members, open_members
from engine.io.codecs import decode_png_fast
from engine.io.completeness import Completeness, check_count, check_numbering
from engine.io.parallel import decode_threads, ordered_map
from engine.io.png_rows import DeviceRows
from engine.params import check_spacing_zyx_mm
from engine.types import Volume

# makes the (z, y, x) array a stack is decoded into: (shape, dtype) -> an uninitialised C-contiguous array
Allocate = Callable[[tuple[int, ...], "np.dtype[Any]"], np.ndarray]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "png"),
    (b"II*\x00", "tiff"),
    (b"MM\x00*", "tiff"),
    (b"II+\x00", "tiff"),
    (b"MM\x00+", "tiff"),
    (b"\xff\xd8\xff", "jpeg"),
    (b"BM", "bmp"),
    (b"\x93NUMPY", "npy"),
)
_UNIT_MM = {"mm": 1.0, "millimeter": 1.0, "cm": 10.0, "centimeter": 10.0, "m": 1000.0, "meter": 1000.0,
            "micron": 1e-3, "um": 1e-3, "\u00b5m": 1e-3, "\u03bcm": 1e-3, "micrometer": 1e-3, "nm": 1e-6,
            "inch": 25.4, "in": 25.4}  # fmt: skip
_PRINT_DPI = {72.0, 96.0, 100.0, 150.0, 200.0, 300.0, 600.0, 1200.0}  # screen/print defaults, not scan geometry
SPACING_HINT = (
    'give the voxel size in mm in z, y, x order (CLI --voxel-size z=..,y=..,x=..; job params "spacing": [z, y, x]; '
    "Python spacing_zyx_mm=(z, y, x))"
)


class StackWarning(UserWarning):
    """Input that was loaded, but changed on the way (e.g. colour slices reduced to luminance)."""


def natural_key(name: str) -> list[object]:
    """Sort key that puts ``img2`` before ``img10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def image_kind(head: bytes) -> str | None:
    """The image/array format of a file from its first bytes: png, tiff, jpeg, bmp, npy, or None."""
    for sig, kind in _SIGNATURES:
        if head.startswith(sig):
            return kind
    return None


def load_slice_zip(path: str | Path, threads: int | None = None) -> npt.NDArray[np.generic]:
    """Read a zip (or tar, or folder) of 2-D grayscale slices (natural name order) into a (z, y, x) array.

    Raises:
        InputError (a ValueError): the archive holds no images, or slices differ in shape or dtype.
    """
    with open_members(path) as members:
        arr, _, _ = _read_slices(members, str(path), InputLimits(), threads=decode_threads(threads))
    return arr


def load_stack(
    members: Members,
    label: str,
    spacing_zyx_mm: tuple[float, float, float] | None,
    limits: InputLimits,
    on_progress: Callable[[float], None] | None = None,
    threads: int | None = None,
    allocate: Allocate | None = None,
    rows: DeviceRows | None = None,
) -> Volume:
    """Build a Volume from the image members of ``members`` (slices, one multi-page TIFF, or one .npy).

    ``on_progress`` is called with the fraction of slices decoded. Slices are decoded on ``threads`` threads
    (default: the CPUs this process may use; 1 decodes serially) into ``allocate(shape, dtype)`` (default
    ``np.empty``); with ``rows``, plain grayscale PNG slices are only inflated on the host and unfiltered on its
    device (``engine.io.png_rows``), the same values. The stack's orientation is not known: the pipeline places it
    by ``engine.params.OrientParams`` (``engine.orient``).

    Raises:
        InputError: no images, mixed shapes/dtypes, too many voxels, or no voxel size.
    """
    names = sorted((m.name for m in members.members if image_kind(m.head)), key=natural_key)
    completeness = check_numbering(names, label) if len(names) > 1 else None  # before decoding: fail fast
    data, fmt, geo = _read_slices(members, label, limits, on_progress, decode_threads(threads), allocate, rows)
    check_count(data.shape[0], label)
    if completeness is None:  # one file: a volume (.npy, multi-page TIFF)
        completeness = Completeness(images=data.shape[0], layout="one volume file")
    spacing, how = _resolve_spacing(spacing_zyx_mm, geo, label)
    source: dict[str, Any] = {
        "format": fmt,
        "container": members.kind,
        "files": len(names),
        "spacing_from": how,
        "completeness": completeness.report(),
    }
    return Volume(data=data, spacing_zyx_mm=spacing, units="raw", source=source)


def _read_slices(
    members: Members,
    label: str,
    limits: InputLimits,
    on_progress: Callable[[float], None] | None = None,
    threads: int = 1,
    allocate: Allocate | None = None,
    rows: DeviceRows | None = None,
) -> tuple[np.ndarray, str, dict[str, Any]]:
    """The image members in natural name order as one (z, y, x) array (made by ``allocate``, default ``np.empty``);
    slices after the first are decoded on ``threads`` threads straight into the array (``engine.io.parallel``), or
    with ``rows`` (PNG slices), inflated there and unfiltered on its device."""
    images = [m for m in members.members if image_kind(m.head)]
    if not images:
        seen = ", ".join(m.name for m in members.members[:3]) or "nothing"
        raise InputError(
            f"expected PNG/TIFF/JPEG/BMP slices, a .npy volume or DICOM files in {label}, found none "
            f"({len(members.members)} unrecognised file(s): {seen})"
        )
    images.sort(key=lambda m: natural_key(m.name))
    kinds = sorted({image_kind(m.head) or "" for m in images})
    if len(images) == 1:
        if kinds[0] == "tiff":  # a multi-page TIFF / BigTIFF: page by page into one array (engine.io.tiff)
            from engine.io.tiff import read_tiff_volume

            make = partial(_allocated, allocate)
            if paged := read_tiff_volume(images[0], label, limits, make, _tiff_geometry, on_progress, threads):
                return paged[0], "tiff", paged[1]
        arr, geo = _decode(images[0], limits)
        arr = arr[None] if arr.ndim == 2 else arr
        limits.check_voxels(arr.shape, label)
        _warn_colour(label, [images[0].name] if "colour" in geo else [], geo)
        return _narrow(arr), kinds[0], geo
    if "npy" in kinds:
        raise InputError(f"expected one .npy volume or 2-D image slices in {label}, got {len(images)} files incl. .npy")
    first, geo = _decode(images[0], limits)
    if first.ndim != 2:
        raise InputError(
            f"expected 2-D slices in {label}, but {images[0].name} holds {first.shape[0]} pages; "
            "give a multi-page TIFF on its own"
        )
    limits.check_voxels((len(images), *first.shape), label)
    out = _allocated(allocate, (len(images), *first.shape), first.dtype)
    out[0] = first
    del first
    coloured = [images[0].name] if "colour" in geo else []
    stage = rows if rows is not None and "png" in kinds and rows.start(out) else None

    def decode_into(k: int) -> tuple[tuple[int, ...], np.dtype[Any], bool]:
        """Decode slice k straight into its plane of ``out`` (on a pool thread), or stage it for the device; its
        shape, dtype, colour flag."""
        plane, data = out[k], None
        if stage is not None:  # read once: staged for the device, or decoded here from the same bytes
            data = images[k].read()
            if stage.take(k, data):
                return plane.shape, plane.dtype, False
        s, g = _decode(images[k], limits, plane, data)
        if s is not plane and s.shape == plane.shape and s.dtype == plane.dtype:  # not decoded in place
            plane[...] = s
        return s.shape, s.dtype, "colour" in g

    try:
        # closed on the way out, also when this loop raises: no pool thread outlives the call
        with contextlib.closing(ordered_map(decode_into, range(1, len(images)), threads)) as decoded:
            for k, (shape, dtype, colour) in enumerate(decoded, start=1):
                if colour:
                    coloured.append(images[k].name)
                if shape != out.shape[1:] or dtype != out.dtype:
                    raise InputError(
                        f"expected every slice to be {out.shape[2]}x{out.shape[1]} {out.dtype} like "
                        f"{images[0].name}, got {shape[-1]}x{shape[0]} {dtype} in {images[k].name}"
                    )
                if stage is not None:
                    stage.ready(k + 1)
                if on_progress is not None:
                    on_progress((k + 1) / len(images))
        for k in stage.finish() if stage is not None else ():
            _decode(images[k], limits, out[k])  # a filter type PNG does not define: libpng says so
    finally:
        if stage is not None:
            stage.close()  # no device copy still runs into ``out`` or out of the staging rows
    _warn_colour(label, coloured, geo)
    return _narrow(out), "+".join(kinds), geo


def _allocated(allocate: Allocate | None, shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray:
    """An uninitialised C-contiguous array from ``allocate`` (checked), else ``np.empty``."""
    if allocate is None:
        return np.empty(shape, dtype)
    out = allocate(shape, dtype)
    if out.shape != shape or out.dtype != dtype or not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError(f"allocate{shape, dtype} gave a {out.shape} {out.dtype} array that cannot be filled in place")
    return out


def _warn_colour(label: str, names: list[str], geo: dict[str, Any]) -> None:
    if names:
        warnings.warn(
            f"{label}: {len(names)} image(s) ({names[0]}...) were not grayscale: {geo.get('colour', 'converted')}; "
            "export grayscale slices to keep the scanner values",
            StackWarning,
            stacklevel=5,
        )


def _decode(
    m: Member, limits: InputLimits, plane: np.ndarray | None = None, data: bytes | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Decode one member (its bytes ``data`` where already read) into a 2-D (or 3-D for multi-page TIFF / npy)
    grayscale array plus geometry hints; a plain grayscale PNG of ``plane``'s shape and type is decoded straight into
    ``plane`` (and ``plane`` returned)."""
    kind = image_kind(m.head)
    if data is None:
        data = m.read() if kind != "npy" else b""
    try:
        if kind == "npy":
            arr = _load_npy(m, limits)
            if arr.ndim not in (2, 3) or arr.dtype.kind not in "biuf":
                raise InputError(
                    f"expected a 2-D or 3-D numeric (z, y, x) array in {m.name}, got {arr.shape} {arr.dtype}"
                )
            return arr, {}
        if kind == "tiff":
            return _decode_tiff(data, plane)
        if kind == "png" and (fast := decode_png_fast(data, plane)) is not None:
            return fast, {}
        import imageio.v3 as iio

        arr = iio.imread(io.BytesIO(data))
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot decode {m.name} as {kind.upper() if kind else 'an image'}: {exc}") from None
    arr, note = _to_gray(arr, colour=arr.ndim == 3)
    return arr, {"colour": note} if note else {}


def _load_npy(m: Member, limits: InputLimits) -> np.ndarray:
    """A .npy array, its shape checked against the voxel limit before the data are read."""
    fmt = np.lib.format
    with m._path.open("rb") if m._path is not None else io.BytesIO(m.read()) as fh:
        version = fmt.read_magic(fh)
        reader = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _, _ = reader(fh)
        limits.check_voxels(tuple(shape), m.name)
        fh.seek(0)
        return np.load(fh, allow_pickle=False)


def _decode_tiff(data: bytes, plane: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """A TIFF's pixels and geometry hints; a one-page grayscale slice of ``plane``'s shape and type is decoded
    straight into ``plane`` (and ``plane`` returned: no temporary slice)."""
    import tifffile

    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        page = tf.pages[0]
        colour = page.samplesperpixel > 1
        into = (
            plane is not None
            and len(tf.pages) == 1
            and not colour
            and tuple(page.shape) == plane.shape
            and np.dtype(page.dtype) == plane.dtype
        )
        if into:
            assert plane is not None
            page.asarray(out=plane)
            arr = plane
        else:
            arr = tf.asarray()
        if colour and int(page.planarconfig) == 2:  # separate colour planes: (..., samples, y, x)
            arr = np.moveaxis(arr, -3, -1)
        geo = _tiff_geometry(tf, page)
    arr, note = _to_gray(arr, colour=colour)
    if note:
        geo["colour"] = note
    return arr, geo


def _tiff_geometry(tf: Any, page: Any) -> dict[str, Any]:
    """(y, x) pixel size and z step in mm from TIFF resolution tags and ImageJ metadata, where they are usable."""
    geo: dict[str, Any] = {}
    ij = tf.imagej_metadata or {}
    unit_mm = None
    res_unit = int(page.tags["ResolutionUnit"].value) if "ResolutionUnit" in page.tags else 2
    if res_unit == 2:
        unit_mm = 25.4
    elif res_unit == 3:
        unit_mm = 10.0
    ij_unit = str(ij.get("unit", "")).strip().lower()
    if ij_unit in _UNIT_MM:
        unit_mm = _UNIT_MM[ij_unit]
    xr, yr = page.tags.get("XResolution"), page.tags.get("YResolution")
    if xr is not None and yr is not None and unit_mm is not None:
        per_unit = [num / den if den else 0.0 for num, den in (yr.value, xr.value)]
        if all(p > 0 and math.isfinite(p) for p in per_unit):
            if unit_mm == 25.4 and not ij_unit and all(round(p, 3) in _PRINT_DPI for p in per_unit):
                geo["note"] = f"its {per_unit[1]:g} dpi resolution tag is a screen/print default, not a voxel size"
            else:
                geo["yx"] = (unit_mm / per_unit[0], unit_mm / per_unit[1])
    z = ij.get("spacing")
    if z is not None and ij_unit in _UNIT_MM and float(z) > 0:
        geo["z"] = float(z) * _UNIT_MM[ij_unit]
    return geo


def _to_gray(arr: np.ndarray, *, colour: bool) -> tuple[np.ndarray, str | None]:
    """Reduce colour (last axis 2..4 channels) to luminance, keeping the dtype; also say what was done."""
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    if not colour or arr.shape[-1] not in (2, 3, 4):
        return arr, None
    if arr.shape[-1] == 2:  # grey + alpha
        return np.ascontiguousarray(arr[..., 0]), "grey+alpha: the alpha channel was dropped"
    rgb = arr[..., :3].astype(np.float32)
    lum = rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114
    note = "colour (RGB) converted to luminance 0.299 R + 0.587 G + 0.114 B"
    if arr.dtype.kind in "iu":
        info = np.iinfo(arr.dtype)
        return np.clip(np.rint(lum), info.min, info.max).astype(arr.dtype), note
    return lum.astype(np.float32), note


def _narrow(arr: np.ndarray) -> np.ndarray:
    """Bring any numeric dtype to one the engine uses (uint8, uint16, int16, float32) without losing values."""
    if arr.dtype in (np.uint8, np.uint16, np.int16, np.float32):
        return arr
    if arr.dtype == np.int8:
        return arr.astype(np.int16)
    if arr.dtype.kind in "iu" and arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        for dt in (np.uint16, np.int16):
            info = np.iinfo(dt)
            if info.min <= lo and hi <= info.max:
                return arr.astype(dt)
    return arr.astype(np.float32)


def _resolve_spacing(
    call: tuple[float, float, float] | None, geo: dict[str, Any], label: str
) -> tuple[tuple[float, float, float], str]:
    if call is not None:
        return call, "call"
    if "yx" in geo and "z" in geo:
        try:
            return check_spacing_zyx_mm((geo["z"], *geo["yx"])), "tiff"
        except ValueError as exc:
            raise InputError(f"{label}: the TIFF tags give an implausible voxel size: {exc}; {SPACING_HINT}") from None
    if "yx" in geo:
        y, x = geo["yx"]
        err = NoSpacingError(
            f"{label}: the TIFF tags give the pixel size (y {y:g} mm, x {x:g} mm) but not the slice spacing; "
            f"give the voxel size in mm in z, y, x order (CLI --voxel-size z=..,y={y:g},x={x:g}; job params "
            f'"spacing": [z, {y:g}, {x:g}]; Python spacing_zyx_mm=(z, {y:g}, {x:g}))'
        )
        err.pixel_yx_mm = (y, x)  # type: ignore[attr-defined]  # for the front ends' own wording (engine.cli.args)
        raise err
    note = f" ({geo['note']})" if "note" in geo else ""
    raise NoSpacingError(f"{label}: an image stack does not carry its voxel size{note}; {SPACING_HINT}")


def check_spacing(spacing: object) -> tuple[float, float, float] | None:
    """Validate a caller's spacing: None, or three finite numbers (z, y, x) in mm within the plausible range
    (``engine.params.SPACING_MM_MIN`` to ``SPACING_MM_MAX``, the range the API accepts).

    Raises:
        InputError: not three numbers, or one of them non-finite, not positive or implausible (1e300, 1e-300).
    """
    if spacing is None:
        return None
    try:
        return check_spacing_zyx_mm(spacing)
    except ValueError as exc:
        raise InputError(str(exc)) from None  # names the axis, so --voxel-size and --spacing read alike
