"""A scan read slab by slab from disk or its store, never whole: the input of a job under a host memory bound
(``engine.budget.Budget.host_bytes``, CLI ``--max-host-bytes``, ``BONEMESH_MAX_HOST_BYTES``).

``open_slabs(path, host_bytes, ...)`` opens the input and reads only its metadata. Where the scan's voxels fit the
bound's share for a whole volume (``Budget.host_volume_share``) it returns None and the scan is loaded whole as
before (``engine.io.load_volume``); otherwise a ``SlabSource``: the shape, sample type, voxel size and origin the
loader would give, and ``read(z0, z1)``, planes ``z0..z1 - 1`` decoded into a new array. The streamed plan
(``engine.job.plans.STREAMED``) reads it slab by slab through the device stages and drops each slab
(``engine.isosurface.feed``); the automatic level reads its strided samples plane by plane (``engine.level``).

What is read slab by slab: a folder, zip or tar of 2-D slices (PNG, TIFF, JPEG, BMP: a file per plane), one
multi-page TIFF or BigTIFF (page by page through tifffile, where its bytes lie: a file, an uncompressed tar's
member, a zip member stored without compression), a ``.npy`` file (each slab read from the file), an OME-Zarr
level (zarr reads the rows of z-chunks a slab spans; the last row read is kept; a box of it, a region of interest,
reads only the chunks inside the box). A DICOM series, a compressed TIFF
archive member, a TIFF without a page per plane and samples of a type the engine does not mesh as they are (int32,
colour .npy) are refused when they do not fit the bound: one line that names a way out.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any, NoReturn, cast

import numpy as np

from engine.budget import mib
from engine.errors import InputError
from engine.types import Volume

__all__ = ["SlabSource", "open_slabs"]

_NATIVE = (np.uint8, np.uint16, np.int16, np.float32)


class SlabSource:
    """A (z, y, x) scan read slab by slab: the array-like ``Volume.data`` of a job out of core.

    ``read(z0, z1)`` gives planes ``z0..z1 - 1`` as a new C-contiguous array of ``dtype``; ``strided(step)`` the
    samples ``data[::step, ::step, ::step]`` (read plane by plane); ``min()`` / ``max()`` a pass over all slabs.
    ``granule``: planes one read decodes at least (a row of Zarr chunks; 1 elsewhere). ``close()`` releases the
    open file or store. ``fill_box(z0, z1, (y0, y1), (x0, x1), out)``, where the source can, decodes only a box of
    the planes (an OME-Zarr's chunks inside it): a box of the scan then reads only what it holds.
    """

    ndim = 3

    def __init__(
        self,
        shape: tuple[int, int, int],
        dtype: np.dtype[Any],
        fill: Callable[[int, int, np.ndarray], None],
        *,
        label: str,
        granule: int = 1,
        close: Callable[[], None] | None = None,
        fill_box: Callable[[int, int, tuple[int, int], tuple[int, int], np.ndarray], None] | None = None,
    ) -> None:
        self.shape, self.dtype, self.label, self.granule = shape, np.dtype(dtype), label, max(1, granule)
        self._fill, self._close, self._fill_box = fill, close, fill_box
        self._range: tuple[float, float] | None = None

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]

    @property
    def itemsize(self) -> int:
        return self.dtype.itemsize

    @property
    def nbytes(self) -> int:
        return self.size * self.itemsize

    @property
    def plane_bytes(self) -> int:
        return self.shape[1] * self.shape[2] * self.itemsize

    def read(self, z0: int, z1: int) -> np.ndarray:
        """Planes ``z0..z1 - 1`` as a new (z1 - z0, y, x) array."""
        z0, z1 = max(0, z0), min(self.shape[0], z1)
        out = np.empty((max(z1 - z0, 0), *self.shape[1:]), self.dtype)
        if z1 > z0:
            self._fill(z0, z1, out)
        return out

    def read_into(self, z0: int, z1: int, out: np.ndarray) -> None:
        """Planes ``z0..z1 - 1`` decoded into ``out`` ((z1 - z0, y, x), C-contiguous, of ``dtype``)."""
        if z1 > z0:
            self._fill(z0, z1, out)

    def __getitem__(self, key: tuple[slice, slice, slice]) -> SlabSource:
        """A box of the scan, ``data[z0:z1, y0:y1, x0:x1]`` (steps of 1 only), as a ``SlabSource`` that reads it:
        the planes it spans read ``granule`` at a time and cut to the box (a region of interest out of core)."""
        if not (isinstance(key, tuple) and len(key) == 3 and all(isinstance(k, slice) for k in key)):
            raise TypeError(f"a scan read slab by slab is cut by a box of three slices, not {key!r}")
        (z0, z1, zs), (y0, y1, ys), (x0, x1, xs) = (k.indices(n) for k, n in zip(key, self.shape, strict=True))
        if (zs, ys, xs) != (1, 1, 1):
            raise TypeError("a scan read slab by slab is cut by a box (steps of 1)")
        shape = (max(z1 - z0, 0), max(y1 - y0, 0), max(x1 - x0, 0))
        step = self.granule
        label = f"{self.label}[box]"
        parent_box = self._fill_box
        if parent_box is not None:  # only the box decoded

            def fill_box(a: int, b: int, ys: tuple[int, int], xs: tuple[int, int], out: np.ndarray) -> None:
                parent_box(z0 + a, z0 + b, (y0 + ys[0], y0 + ys[1]), (x0 + xs[0], x0 + xs[1]), out)

            def fill_in_box(a: int, b: int, out: np.ndarray) -> None:
                fill_box(a, b, (0, shape[1]), (0, shape[2]), out)

            return SlabSource(shape, self.dtype, fill_in_box, label=label, granule=step, close=self.close,
                              fill_box=fill_box)  # fmt: skip

        def fill(a: int, b: int, out: np.ndarray) -> None:
            for z in range(a, b, step):
                top = min(z + step, b)
                out[z - a : top - a] = self.read(z0 + z, z0 + top)[:, y0:y1, x0:x1]

        return SlabSource(shape, self.dtype, fill, label=label, granule=step, close=self.close)

    def strided(self, step: int) -> np.ndarray:
        """``data[::step, ::step, ::step]``, read one plane at a time."""
        zs = range(0, self.shape[0], step)
        out = np.empty((len(zs), -(-self.shape[1] // step), -(-self.shape[2] // step)), self.dtype)
        for i, z in enumerate(zs):
            out[i] = self.read(z, z + 1)[0, ::step, ::step]
        return out

    def _minmax(self) -> tuple[float, float]:
        if self._range is None:
            lo, hi = float("inf"), float("-inf")
            step = max(self.granule, (64 << 20) // max(self.plane_bytes, 1))
            for z in range(0, self.shape[0], step):
                slab = self.read(z, z + step)
                lo, hi = min(lo, float(slab.min())), max(hi, float(slab.max()))
            self._range = (lo, hi)
        return self._range

    def min(self) -> float:
        return self._minmax()[0]

    def max(self) -> float:
        return self._minmax()[1]

    def close(self) -> None:
        if self._close is not None:
            self._close()
            self._close = None

    def __repr__(self) -> str:
        return f"SlabSource({self.label}, shape={self.shape}, dtype={self.dtype})"


def open_slabs(
    path: str | Path,
    whole_bytes: int,
    *,
    spacing_zyx_mm: tuple[float, float, float] | None = None,
    level: int | str | None = None,
    limits: Any = None,
    threads: int | None = None,
) -> Volume | None:
    """The scan at ``path`` as a ``Volume`` whose ``data`` is a ``SlabSource``, where its voxels take more than
    ``whole_bytes`` (the host bound's share for a whole volume); None where they fit it (load it whole).

    Raises:
        InputError: the scan does not fit and cannot be read slab by slab (the message names a way out), or as
            ``engine.io.load_volume``.
    """
    from engine.io import InputLimits
    from engine.io.archive import open_members
    from engine.io.dicom import has_dicom_images
    from engine.io.omezarr import ZarrSource, is_remote, zarr_in
    from engine.io.parallel import decode_threads
    from engine.io.stack import check_spacing

    spacing = check_spacing(spacing_zyx_mm)
    limits = limits or InputLimits()
    threads = decode_threads(threads)
    if is_remote(path):
        return _zarr(ZarrSource("s3", str(path)), whole_bytes, spacing, level, limits)
    stack = contextlib.ExitStack()
    try:
        members = stack.enter_context(open_members(path, limits))
        label = Path(path).name or str(path)
        if (src := zarr_in(members, Path(path))) is not None:
            stack.close()
            return _zarr(src, whole_bytes, spacing, level, limits)
        if level is not None:  # load_volume's refusal
            raise InputError(f"level={level!r} was given, but {label} is not an OME-Zarr image")
        if has_dicom_images(members):
            total = sum(m.size for m in members.members)
            if total > whole_bytes:
                raise InputError(
                    f"{label} is a DICOM series of about {mib(total)}, over the host memory bound's "
                    f"{mib(whole_bytes)} for a whole scan, and DICOM is not read slab by slab: give a larger "
                    f"--max-host-bytes (at least {mib(_whole_bound(total))}) or convert it to a TIFF folder or OME-Zarr"
                )
            stack.close()
            return None
        vol = _stack(members, label, whole_bytes, spacing, limits, stack, threads)
    except BaseException:
        stack.close()
        raise
    if vol is None:
        stack.close()
    else:  # the files (and a TIFF's handle) stay open while the job reads them
        cast(Any, vol.data)._close = stack.close
    return vol


def _whole_bound(nbytes: int) -> int:
    """The host bound under which a whole volume of ``nbytes`` is read whole."""
    from engine.budget import Budget

    return int(nbytes / Budget().host_volume_share) + 1


def _zarr(src: Any, whole_bytes: int, spacing: Any, level: int | str | None, limits: Any) -> Volume | None:
    from engine.io.omezarr import open_level, read_planes, z_step

    lv = open_level(src, level=level, spacing_zyx_mm=spacing, limits=limits)
    nbytes = int(np.prod(lv.shape)) * (lv.target.itemsize if lv.target is not None else 4)
    if nbytes <= whole_bytes:
        return None
    if lv.target is None:
        raise InputError(
            f"{lv.where}: its samples are {lv.arr.dtype}, which are narrowed over the whole scan before meshing; "
            f"give a --max-host-bytes of at least {mib(_whole_bound(nbytes))} or store them as uint16 or float32"
        )
    target = lv.target
    step = z_step(lv)
    cache: dict[str, Any] = {"key": None, "row": None}

    def fill_box(z0: int, z1: int, ys: tuple[int, int], xs: tuple[int, int], out: np.ndarray) -> None:
        if z1 - z0 >= step:  # a slab of rows: read as it is
            read_planes(lv, z0, z1, out, ys, xs)
            return
        z = z0
        while z < z1:  # short reads (a plane, a halo) from the row of chunks that holds them, kept for the next
            r0 = z // step * step
            if cache["key"] != (r0, ys, xs):
                row = np.empty((min(r0 + step, lv.shape[0]) - r0, ys[1] - ys[0], xs[1] - xs[0]), target)
                read_planes(lv, r0, r0 + len(row), row, ys, xs)
                cache["key"], cache["row"] = (r0, ys, xs), row
            n = min(z1, r0 + len(cache["row"])) - z
            out[z - z0 : z - z0 + n] = cache["row"][z - r0 : z - r0 + n]
            z += n

    def fill(z0: int, z1: int, out: np.ndarray) -> None:
        fill_box(z0, z1, (0, lv.shape[1]), (0, lv.shape[2]), out)

    def drop() -> None:
        cache["row"] = None

    data = SlabSource(lv.shape, target, fill, label=lv.where, granule=step, close=drop, fill_box=fill_box)
    source = {**lv.source, "read": "slab by slab (host memory bound)"}
    return Volume(data=_as_data(data), spacing_zyx_mm=lv.spacing, origin_mm=lv.origin, units="raw", source=source)


def _as_data(src: SlabSource) -> Any:
    """``Volume.data`` is typed as an array; out of core it is a ``SlabSource`` (the stages that read it check)."""
    return src


def _stack(
    members: Any, label: str, whole_bytes: int, spacing: Any, limits: Any, stack: contextlib.ExitStack, threads: int
) -> Volume | None:
    """A stack of 2-D slices, one multi-page TIFF or one .npy, slab by slab (None where it fits whole)."""
    from engine.io.completeness import Completeness, check_count, check_numbering
    from engine.io.stack import _decode, _resolve_spacing, image_kind, natural_key

    images = sorted((m for m in members.members if image_kind(m.head)), key=lambda m: natural_key(m.name))
    if not images:
        return None  # load_volume says what is missing
    kind = image_kind(images[0].head)
    if len(images) == 1 and kind == "npy":
        return _npy(images[0], label, whole_bytes, spacing, limits, members.kind)
    if len(images) == 1 and kind == "tiff":
        return _tiff(images[0], label, whole_bytes, spacing, limits, members.kind, stack, threads)
    if len(images) == 1:
        return None  # one 2-D image
    completeness = check_numbering([m.name for m in images], label)
    first, geo = _decode(images[0], limits)
    if first.ndim != 2:
        return None  # load_volume refuses it
    shape = (len(images), int(first.shape[0]), int(first.shape[1]))
    limits.check_voxels(shape, label)
    nbytes = int(np.prod(shape)) * first.dtype.itemsize
    if nbytes <= whole_bytes:
        return None
    if first.dtype.type not in _NATIVE:
        raise InputError(
            f"{label}: its slices are {first.dtype}, which are narrowed over the whole scan before meshing; give a "
            f"--max-host-bytes of at least {mib(_whole_bound(nbytes))} or export uint8, uint16 or float32 slices"
        )
    check_count(shape[0], label)
    dtype = first.dtype
    del first

    def decode(k: int, out: np.ndarray) -> None:
        got, _ = _decode(images[k], limits, out)
        if got.shape != shape[1:] or got.dtype != dtype:
            raise InputError(
                f"expected every slice to be {shape[2]}x{shape[1]} {dtype} like {images[0].name}, got "
                f"{got.shape[-1]}x{got.shape[0]} {got.dtype} in {images[k].name}"
            )
        if got is not out:
            out[...] = got

    fill = _planewise(decode, threads)

    sp, how = _resolve_spacing(spacing, geo, label)
    kinds = "+".join(sorted({image_kind(m.head) or "" for m in images}))
    source = {"format": kinds, "container": members.kind, "files": len(images), "spacing_from": how}
    source |= {"completeness": (completeness or Completeness(images=shape[0], layout="stack")).report()}
    source["read"] = "slab by slab (host memory bound)"
    data = SlabSource(shape, dtype, fill, label=label)
    return Volume(data=_as_data(data), spacing_zyx_mm=sp, units="raw", source=source)


def _npy(m: Any, label: str, whole_bytes: int, spacing: Any, limits: Any, container: str) -> Volume | None:
    """A (z, y, x) .npy file, each slab read from the file straight into its array (not memory-mapped: mapped pages
    stay in the process's resident set once read)."""
    from engine.io.stack import _resolve_spacing

    if m._path is None:
        return None if m.size <= whole_bytes else _refuse_member(label, m.size, "a .npy inside an archive")
    fmt = np.lib.format
    with m._path.open("rb") as fh:
        version = fmt.read_magic(fh)
        reader = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape_, fortran, dtype_ = reader(fh)
        offset = fh.tell()
    dtype_ = np.dtype(dtype_)
    nbytes = int(np.prod(shape_)) * dtype_.itemsize
    if len(shape_) != 3 or nbytes <= whole_bytes:
        return None
    limits.check_voxels(tuple(shape_), label)
    native = dtype_.newbyteorder("=")
    if native.type not in _NATIVE or fortran:
        what = f"samples are {dtype_}" if native.type not in _NATIVE else "array is in Fortran order"
        raise InputError(
            f"{label}: its {what}, which is read whole before meshing; give a --max-host-bytes of at least "
            f"{mib(_whole_bound(nbytes))} or save it as a C-ordered uint16 or float32 array"
        )
    shape = (int(shape_[0]), int(shape_[1]), int(shape_[2]))
    plane = shape[1] * shape[2] * dtype_.itemsize
    path = m._path

    def fill(z0: int, z1: int, out: np.ndarray) -> None:
        with path.open("rb") as fh:
            fh.seek(offset + z0 * plane)
            view = out.reshape(-1).view(np.uint8)
            if fh.readinto(memoryview(view)) != view.size:
                raise InputError(f"{label}: the file ends before slice {z1 - 1}")
        if dtype_ != native:  # another byte order: swapped in place
            out.byteswap(inplace=True)

    sp, how = _resolve_spacing(spacing, {}, label)
    source = {"format": "npy", "container": container, "files": 1, "spacing_from": how}
    source |= {"read": "slab by slab (host memory bound)"}
    data = SlabSource(shape, native, fill, label=label)
    return Volume(data=_as_data(data), spacing_zyx_mm=sp, units="raw", source=source)


def _tiff(
    m: Any,
    label: str,
    whole_bytes: int,
    spacing: Any,
    limits: Any,
    container: str,
    stack: contextlib.ExitStack,
    threads: int,
) -> Volume | None:
    """One multi-page TIFF / BigTIFF, page by page (``engine.io.tiff``)."""
    from engine.io.stack import _resolve_spacing, _tiff_geometry
    from engine.io.tiff import _in_place, _opened, _page_stack

    if _in_place(m) is None:  # a compressed archive member: read whole into memory to seek in it
        return None if 2 * m.size <= whole_bytes else _refuse_member(label, m.size, "a compressed archive member")
    tf = stack.enter_context(_opened(m))
    found = _page_stack(tf)
    if found is None:
        return None  # colour, several series: load_volume decodes it whole (or refuses it)
    shape, dtype, pages = found
    limits.check_voxels(shape, label)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if nbytes <= whole_bytes:
        return None
    if pages is None:
        raise InputError(
            f"{label}: its frames have no page of their own (an ImageJ hyperstack over 4 GB), so it is not read "
            f"page by page; give a --max-host-bytes of at least {mib(_whole_bound(nbytes))} or save it as a TIFF "
            "folder or OME-Zarr"
        )
    geo = _tiff_geometry(tf, tf.pages[0])

    if threads > 1:
        tf.filehandle.set_lock(True)  # the file's reads serialised, the pages decoded side by side

    def decode(k: int, out: np.ndarray) -> None:
        try:
            got = pages[k].asarray(out=out, maxworkers=1)
        except Exception as exc:
            raise InputError(f"cannot decode page {k} of {m.name} as TIFF: {exc}") from None
        if got is not out:
            out[...] = got

    fill = _planewise(decode, threads)

    sp, how = _resolve_spacing(spacing, geo, label)
    source = {"format": "tiff", "container": container, "files": 1, "spacing_from": how}
    source |= {"read": "slab by slab (host memory bound)"}
    data = SlabSource((int(shape[0]), int(shape[1]), int(shape[2])), dtype, fill, label=label)
    return Volume(data=_as_data(data), spacing_zyx_mm=sp, units="raw", source=source)


def _planewise(decode: Callable[[int, np.ndarray], None], threads: int) -> Callable[[int, int, np.ndarray], None]:
    """A ``fill`` that decodes each plane ``k`` into its place (``decode(k, plane)``) on ``threads`` threads."""
    from engine.io.parallel import ordered_map

    def fill(z0: int, z1: int, out: np.ndarray) -> None:
        if threads <= 1 or z1 - z0 == 1:
            for k in range(z0, z1):
                decode(k, out[k - z0])
            return
        planes = ordered_map(lambda k: decode(k, out[k - z0]), range(z0, z1), threads)
        with contextlib.closing(cast(Generator[None, None, None], planes)) as done:
            for _ in done:
                pass

    return fill


def _refuse_member(label: str, size: int, what: str) -> NoReturn:
    raise InputError(
        f"{label}: the scan is {what} of about {mib(size)}, which is read whole, over the host memory bound: give a "
        f"larger --max-host-bytes (at least {mib(_whole_bound(2 * size))}) or unpack it"
    )
