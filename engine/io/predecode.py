"""A zip of PNG slices decoded while it is still arriving, into a volume file beside it (the "sidecar").

:class:`UploadDecoder` is fed an upload's bytes in order as they arrive (``feed``: by default a child process of the API
reads them from the upload's file as it grows, ``engine.io.predecode_proc``; else the API's upload writer hands it the
same batches it writes, views of the received bytes: a member's bytes are not copied until its decoding thread joins
them). The archive is read front to back (``engine.io.zipstream``); each PNG member, once all its bytes are there, is
inflated and decoded on a small thread pool (``engine.io.codecs.decode_png_fast``, the loader's own decoder) straight
into its plane of ``<upload>.slices`` (raw samples, plane after plane in the order the members came; or, in the
``"rows"`` layout, only inflated: the PNG's filtered rows, every row's filter type checked, for the worker's GPU to
unfilter as it does for the slices it decodes itself, ``engine.io.png_rows``: about a third of a slice's decoding, the
rest left to the device), while later bytes still arrive: memory holds only the members being decoded
(``backlog_bytes``; past it, ``feed`` waits for the pool). ``finish`` (the upload complete) checks that the members
decoded are exactly the stack the loader would read from the complete archive, in its order (:func:`stack_order`: the
loader's own listing, sorting and choice of images, every member's offset, CRC and sizes as its central directory gives
them), and writes ``<upload>.slices.json`` (shape, sample type, upload size, the members, the loader's order): only then
is the sidecar there. Anything it does not follow (an image member not a plain grayscale PNG, a DICOM member, slices of
different shapes, what ``engine.io.zipstream`` cannot stream, a write that fails) stops it quietly and removes its
files: the upload goes on, and the worker decodes the archive as before. ``abort`` removes them too. Members that are no
image (by the loader's own test of their first bytes) are passed by, as the loader does.

:func:`load_predecoded` gives the :class:`Volume` the loader would give (``engine.io.load_volume``: the same samples,
spacing and report, ``source["decoded_during_upload"]``), read from a sidecar that is still the upload's (checked again
as ``finish`` did, and written since the host last booted: the planes are not fsynced, for the upload's sake, so after a
crash they are not trusted), or None (then load the upload as before). Rows are unfiltered on the job's GPU
(``DeviceRows``) where it has one, else by libpng on the host's threads. Under a host memory bound it gives a
``engine.io.slabs.SlabSource`` reading the planes from the file (rows unfiltered by libpng).
"""

from __future__ import annotations

import contextlib
import json
import os
import struct
import threading
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from engine.io.archive import HEAD_BYTES, InputLimits, is_junk, open_members
from engine.io.codecs import (
    can_unfilter,
    decode_png_fast,
    filters_known,
    inflate_rows,
    plain_gray_png,
    rows_bytes,
    unfilter_rows,
)
from engine.io.dicom import has_dicom_images, looks_like_dicom
from engine.io.stack import image_kind, natural_key
from engine.io.zipstream import ZipEntry, ZipStream

if TYPE_CHECKING:
    from engine.io.png_rows import DeviceRows
    from engine.types import Volume

__all__ = ["UploadDecoder", "load_predecoded", "remove_predecoded", "sidecar_paths", "stack_order"]

VERSION = 1
BACKLOG_BYTES = 64 << 20  # members waiting for the pool (views of the received bytes); past it, feed waits
READ_BYTES = 64 << 20  # planes read at a time when a sidecar is loaded
PLANES, ROWS = "planes", "rows"  # what a sidecar's planes hold: samples, or the PNG's filtered rows (the layouts)


def sidecar_paths(upload: Path) -> tuple[Path, Path]:
    """The sidecar of ``upload``: its planes and its manifest."""
    return upload.with_name(upload.name + ".slices"), upload.with_name(upload.name + ".slices.json")


def remove_predecoded(upload: Path) -> None:
    """Remove the sidecar of ``upload`` (never raises)."""
    data, manifest = sidecar_paths(upload)
    for path in (data, manifest, manifest.with_name(manifest.name + ".tmp")):
        with contextlib.suppress(OSError):
            path.unlink()


class UploadDecoder:
    """Decodes the PNG slices of a zip upload as its bytes arrive (see the module docstring). ``feed``, ``finish``
    and ``abort`` never raise; ``reason`` says why it stopped, where it did."""

    def __init__(
        self, upload: Path, *, threads: int = 2, backlog_bytes: int = BACKLOG_BYTES, layout: str = PLANES
    ) -> None:
        if layout not in (PLANES, ROWS):
            raise ValueError(f"layout must be {PLANES!r} or {ROWS!r}, got {layout!r}")
        self.upload = Path(upload)
        self.layout = layout
        self.data_path, self.manifest_path = sidecar_paths(self.upload)
        self.stream = ZipStream()
        self.backlog_bytes = backlog_bytes
        self.reason: str | None = None
        self.fed = 0
        self.members: list[dict[str, Any]] = []  # in the order they came: plane k is members[k]'s (PNG or not)
        self.shape: tuple[int, int] | None = None
        self.dtype: np.dtype[Any] | None = None
        self._lock = threading.Condition()
        self._pending = 0  # bytes of members given to the pool, not yet decoded
        self._local = threading.local()
        self._fd: int | None = None
        self._pool: ThreadPoolExecutor | None = None
        try:
            self._fd = os.open(self.data_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            self._pool = ThreadPoolExecutor(max(1, threads), thread_name_prefix="predecode")
        except OSError as exc:
            self._stop(f"cannot write the sidecar: {exc}")

    @property
    def stopped(self) -> bool:
        return self.reason is not None

    def stop(self, reason: str) -> None:
        """Stop decoding (``finish`` then keeps nothing; ``reason`` says why)."""
        self._stop(reason)

    def _stop(self, reason: str) -> None:
        with self._lock:
            if self.reason is None:
                self.reason = reason
            self._lock.notify_all()

    def feed(self, batch: list[memoryview] | list[bytes]) -> None:
        """The upload's next bytes."""
        if self.stopped:
            return
        try:
            for view in batch:
                self.fed += len(view)
                for entry in self.stream.feed(view):
                    self._submit(entry)
                if self.stopped:
                    return
        except Exception as exc:  # CannotStream, a pool that is gone, ...: the upload goes on without it
            self._stop(f"{type(exc).__name__}: {exc}")

    def _submit(self, entry: ZipEntry) -> None:
        if entry.name.endswith("/") or is_junk(entry.name):
            return
        k = len(self.members)
        record = {"name": entry.name, "offset": entry.offset, "crc": entry.crc, "compress_size": entry.compress_size,
                  "file_size": entry.file_size, "png": False}  # fmt: skip
        self.members.append(record)
        size = entry.stored_bytes
        with self._lock:  # memory holds at most backlog_bytes of members waiting (the upload waits meanwhile)
            while self._pending and self._pending + size > self.backlog_bytes and self.reason is None:
                self._lock.wait()
            if self.reason is not None:
                return
            self._pending += size
        assert self._pool is not None
        self._pool.submit(self._decode, k, entry, size)

    def _decode(self, k: int, entry: ZipEntry, size: int) -> None:
        try:
            if not self.stopped:
                self._decode_into(k, entry)
        except Exception as exc:
            self._stop(f"{entry.name}: {type(exc).__name__}: {exc}")
        finally:
            with self._lock:
                self._pending -= size
                self._lock.notify_all()

    def _decode_into(self, k: int, entry: ZipEntry) -> None:
        kind = image_kind(head := entry.head(HEAD_BYTES))  # the loader's tests of a member, on its first bytes
        if kind not in ("png", None) or looks_like_dicom(head):
            raise ValueError(f"a {kind or 'DICOM'} member: not a stack of PNG slices")
        if kind is None:
            return  # not an image (notes, a checksum file): the loader passes it by
        data = entry.content()
        if not plain_gray_png(data):
            raise ValueError("not a plain grayscale PNG")
        width, height, depth = struct.unpack(">IIB", data[16:25])
        dtype = np.dtype(np.uint8 if depth == 8 else np.uint16)
        with self._lock:
            if self.shape is None:
                self.shape, self.dtype = (height, width), dtype
        if (height, width) != self.shape or dtype != self.dtype:
            raise ValueError(f"{width}x{height} {dtype}, unlike the slices before it")
        view = self._rows(data) if self.layout == ROWS else self._samples(data)
        assert self._fd is not None
        at = k * len(view)
        while view:
            n = os.pwrite(self._fd, view, at)
            view, at = view[n:], at + n
        self.members[k]["png"] = True

    def _samples(self, data: bytes) -> memoryview:
        """A slice's samples (libpng), in this thread's plane."""
        assert self.shape is not None and self.dtype is not None
        plane = getattr(self._local, "plane", None)
        if plane is None or plane.shape != self.shape or plane.dtype != self.dtype:
            plane = self._local.plane = np.empty(self.shape, self.dtype)
        arr = decode_png_fast(data, plane)
        if arr is None or arr.shape != plane.shape or arr.dtype != self.dtype:
            raise ValueError("not decoded by libpng")
        return np.ascontiguousarray(arr).reshape(-1).view(np.uint8).data

    def _rows(self, data: bytes) -> memoryview:
        """A slice's filtered rows (only inflated: the worker's GPU unfilters them), in this thread's buffer; every
        row's filter type checked, so that unfiltering them later cannot fail."""
        assert self.shape is not None and self.dtype is not None
        size = rows_bytes(self.shape, self.dtype)
        buf = getattr(self._local, "rows", None)
        if buf is None or len(buf) != size:
            buf = self._local.rows = memoryview(bytearray(size))
        if not inflate_rows(data, self.shape, self.dtype, buf) or not filters_known(buf, self.shape, self.dtype):
            raise ValueError("its rows do not inflate to what its header says")
        return buf

    def _drain(self, cancel: bool = False) -> None:
        """Wait for the pool (its members not yet begun dropped where ``cancel``) and close the file."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel)
            self._pool = None
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def abort(self) -> None:
        """Stop and remove the sidecar (a refused upload keeps nothing)."""
        self._stop("aborted")
        self._drain(cancel=True)
        remove_predecoded(self.upload)

    def finish(self, limits: InputLimits | None = None) -> bool:
        """The upload is complete (and at ``upload``): keep the sidecar where it is the loader's stack (True), else
        remove it (False; ``reason`` says why)."""
        try:
            self._drain()
            if self.reason is None and not self.stream.ended:
                self.reason = "the archive's central directory never came"
            if self.reason is None and self.fed != self.upload.stat().st_size:
                self.reason = "the upload is not the bytes fed"
            if self.reason is None and self.shape is None:
                self.reason = "no PNG slice"
            if self.reason is not None:
                raise _Drop
            assert self.shape is not None and self.dtype is not None
            manifest = {
                "version": VERSION,
                "boot_id": boot_id(),
                "upload_bytes": self.fed,
                "shape": [len(self.members), *self.shape],
                "dtype": self.dtype.str,
                "layout": self.layout,
                "members": self.members,
            }
            order = stack_order(self.upload, manifest, limits)
            if order is None:
                self.reason = "not the stack the loader reads"
                raise _Drop
            manifest["order"] = order
            tmp = self.manifest_path.with_name(self.manifest_path.name + ".tmp")
            tmp.write_text(json.dumps(manifest))
            os.replace(tmp, self.manifest_path)
            return True
        except Exception as exc:
            if not isinstance(exc, _Drop):
                self.reason = f"{type(exc).__name__}: {exc}"
            remove_predecoded(self.upload)
            with contextlib.suppress(OSError):
                self.manifest_path.with_name(self.manifest_path.name + ".tmp").unlink()
            return False


class _Drop(Exception):
    """The sidecar is not kept (``UploadDecoder.reason`` says why)."""


def stack_order(upload: Path, manifest: dict[str, Any], limits: InputLimits | None = None) -> list[int] | None:
    """The planes of the sidecar in the order the loader reads the upload's slices (``engine.io.load_volume``: its
    listing, its choice of images and its sorting), or None where the sidecar does not hold exactly them: the upload
    is not a zip of two or more PNG slices (no DICOM, no Zarr), a slice was not decoded, or a member's offset, CRC
    or sizes are not those of the archive's central directory."""
    from engine.io.omezarr import zarr_in

    with open_members(upload, limits or InputLimits(), heads_only=True) as members:
        if members.kind != "zip" or zarr_in(members, upload) is not None or has_dicom_images(members):
            return None
        images = [m for m in members.members if image_kind(m.head)]
        images.sort(key=lambda m: natural_key(m.name))  # as engine.io.stack._read_slices
        if len(images) < 2 or any(image_kind(m.head) != "png" for m in images):
            return None
        names = [m.name for m in images]
    with zipfile.ZipFile(upload) as zf:
        infos = zf.infolist()
    central = {i.filename: i for i in infos}
    planes = {m["name"]: k for k, m in enumerate(manifest["members"])}
    if len(central) != len(infos) or len(planes) != len(manifest["members"]):
        return None  # a name twice: which one the loader reads is not for the sidecar to guess
    order = []
    for name in names:
        k, info = planes.get(name), central.get(name)
        if k is None or info is None:
            return None
        m = manifest["members"][k]
        seen = (m["png"], m["offset"], m["crc"], m["compress_size"], m["file_size"])
        if seen != (True, info.header_offset, info.CRC, info.compress_size, info.file_size):
            return None
        order.append(k)
    return order


def load_predecoded(
    path: str | Path,
    *,
    spacing_zyx_mm: Any = None,
    limits: InputLimits | None = None,
    allocate: Callable[[tuple[int, ...], np.dtype[Any]], np.ndarray] | None = None,
    threads: int | None = None,
    whole_bytes: int | None = None,
    rows: DeviceRows | None = None,
) -> Volume | None:
    """The volume of the upload at ``path`` read from its sidecar (see the module docstring), or None. A sidecar of
    filtered rows is unfiltered on ``rows``' device (a GPU's, ``engine.io.png_rows``) where given, else on the host
    (libpng, on ``threads`` threads).

    Raises:
        InputError: as ``engine.io.load_volume`` for this stack (holes in its numbering, too few slices, too many
            voxels, no voxel size).
    """
    from engine.io.completeness import check_count, check_numbering
    from engine.io.parallel import decode_threads
    from engine.io.stack import _resolve_spacing, check_spacing
    from engine.types import Volume

    path = Path(path)
    limits = limits or InputLimits()
    data_path, manifest_path = sidecar_paths(path)
    try:
        manifest = json.loads(manifest_path.read_text())
        z, h, w = (int(n) for n in manifest["shape"])
        dtype = np.dtype(manifest["dtype"])
        layout = manifest.get("layout", PLANES)
        ok = (
            layout in (PLANES, ROWS)
            and manifest.get("version") == VERSION
            and manifest["upload_bytes"] == path.stat().st_size
        )
        # written since this host last booted: its planes are not fsynced (the upload's latency), so a crash may
        # have lost them while the manifest survived
        booted = boot_id()
        ok = ok and booted is not None and manifest.get("boot_id") == booted
        ok = ok and (layout == PLANES or rows is not None or can_unfilter())  # rows: a device, or libpng here
        order = stack_order(path, manifest, limits) if ok else None
        plane = rows_bytes((h, w), dtype) if layout == ROWS else h * w * dtype.itemsize
        if order is None or not (max(order) + 1) * plane <= data_path.stat().st_size <= z * plane:
            return None
    except Exception:  # no sidecar, or not this upload's: the loader reads the upload (and says what is wrong)
        return None
    if order is None or order != manifest["order"]:
        return None
    label = path.name or str(path)
    names = [manifest["members"][k]["name"] for k in order]
    completeness = check_numbering(names, label)
    shape = (len(order), h, w)
    limits.check_voxels(shape, label)
    check_count(len(order), label)
    spacing, how = _resolve_spacing(check_spacing(spacing_zyx_mm), {}, label)
    source = {"format": "png", "container": "zip", "files": len(names), "spacing_from": how,
              "completeness": completeness.report(), "decoded_during_upload": True}  # fmt: skip
    reader = _Planes(data_path, order, (h, w), dtype, decode_threads(threads), layout)
    nbytes = len(order) * h * w * dtype.itemsize
    if whole_bytes is not None and nbytes > whole_bytes:  # under a host memory bound: slab by slab
        from engine.io.slabs import SlabSource

        data: Any = SlabSource(shape, dtype, reader.fill, label=label, close=reader.close)
    else:
        data = np.empty(shape, dtype) if allocate is None else allocate(shape, dtype)
        try:
            if layout == ROWS and rows is not None and rows.start(data, staging=False):
                reader.to_device(rows, data)
            else:
                reader.fill(0, len(order), data)
        except _Unreadable:  # never expected (the decoder checked every row): the loader reads the upload
            return None
        finally:
            reader.close()
    return Volume(data=data, spacing_zyx_mm=spacing, units="raw", source=source)


def boot_id() -> str | None:
    """This host's boot id (Linux; None elsewhere: then no sidecar is trusted)."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip() or None
    except OSError:
        return None


class _Unreadable(Exception):
    """A sidecar's rows that do not unfilter (the decoder checked them: never expected)."""


class _Planes:
    """Planes of a sidecar read into arrays, in the loader's order (runs of consecutive planes read at once, on
    ``threads`` threads); a sidecar of filtered rows (``layout`` ``"rows"``) unfiltered on the host plane by plane
    (``fill``) or on a GPU (``to_device``)."""

    def __init__(
        self, path: Path, order: list[int], shape: tuple[int, int], dtype: np.dtype[Any], threads: int, layout: str
    ) -> None:
        self.fd: int | None = os.open(path, os.O_RDONLY)
        self.order, self.threads, self.layout = order, threads, layout
        self.shape, self.dtype = shape, dtype
        self.plane = rows_bytes(shape, dtype) if layout == ROWS else shape[0] * shape[1] * dtype.itemsize
        self._local = threading.local()

    def _runs(self, z0: int, z1: int, per: int) -> list[tuple[int, int, int]]:
        """(first plane of the output, first plane of the file, count): consecutive planes, at most ``per``."""
        runs, z = [], z0
        while z < z1:
            n = 1
            while z + n < z1 and n < per and self.order[z + n] == self.order[z] + n:
                n += 1
            runs.append((z - z0, self.order[z], n))
            z += n
        return runs

    def _read(self, into: np.ndarray, k: int) -> None:
        """File planes from ``k`` into ``into`` (uint8, planes of the file's size)."""
        assert self.fd is not None
        view, at = into.reshape(-1).data, k * self.plane
        while view:
            got = os.preadv(self.fd, [view], at)
            if got <= 0:
                raise OSError(f"the sidecar ends before plane {k}")
            view, at = view[got:], at + got

    def _map(self, fn: Callable[[Any], None], items: list[Any]) -> None:
        if self.threads <= 1 or len(items) <= 1:
            for item in items:
                fn(item)
            return
        with ThreadPoolExecutor(min(self.threads, len(items))) as pool:
            list(pool.map(fn, items))

    def fill(self, z0: int, z1: int, out: np.ndarray) -> None:
        if self.layout == ROWS:
            self._map(lambda z: self._unfilter(z, out[z - z0]), list(range(z0, z1)))
            return
        flat = out.reshape(z1 - z0, -1).view(np.uint8)
        runs = self._runs(z0, z1, max(1, READ_BYTES // max(self.plane, 1)))
        self._map(lambda run: self._read(flat[run[0] : run[0] + run[2]], run[1]), runs)

    def _unfilter(self, z: int, out: np.ndarray) -> None:
        """Plane ``z``'s rows, read into this thread's buffer and unfiltered into ``out`` on the host."""
        buf = getattr(self._local, "rows", None)
        if buf is None:
            buf = self._local.rows = np.empty((1, self.plane), np.uint8)
        self._read(buf, self.order[z])
        if not unfilter_rows(buf.reshape(-1).data, self.shape, self.dtype, out):
            raise _Unreadable(f"plane {self.order[z]}")

    def to_device(self, rows: DeviceRows, out: np.ndarray) -> None:
        """The rows unfiltered by ``rows``' device (started on ``out`` without staging) into ``out``, a slab at a
        time through a ring of two slabs' rows (page-locked on a CUDA device): the next slab is read while the
        device works on the one before, and no staging array the volume's size is needed."""
        z, slab = len(self.order), rows.slab
        shape = (min(z, 2 * slab), self.plane)
        ring = np.empty(shape, np.uint8) if rows.allocate is None else rows.allocate(shape, np.dtype(np.uint8))
        slabs = [(lo, min(z, lo + slab)) for lo in range(0, z, slab)]
        per = max(1, READ_BYTES // max(self.plane, 1))
        try:
            with ThreadPoolExecutor(max(1, self.threads)) as pool:

                def read(s: int) -> list[Any]:  # slab s's rows into its half of the ring, on the pool
                    lo, hi = slabs[s]
                    half = ring[(s % 2) * slab :][: hi - lo]
                    return [pool.submit(self._read, half[i : i + n], k) for i, k, n in self._runs(lo, hi, per)]

                reading = read(0)
                for s, (lo, hi) in enumerate(slabs):
                    for done in reading:
                        done.result()
                    if s + 1 < len(slabs):
                        if s >= 1:  # the next slab's half held slab s - 1: the device must have taken it
                            rows.backend.synchronize()
                        reading = read(s + 1)
                    rows.send_rows(lo, hi, ring[(s % 2) * slab :][: hi - lo])
            if rows.finish():
                raise _Unreadable("a filter type the device does not know")
        finally:
            rows.close()

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
