"""How a listed member's bytes are read: from this process's threads, or from another process.

In this process a zip member is decompressed through a ``ZipFile`` handle of the reading thread's own
(:class:`ZipHandles`) and an uncompressed tar's member is read in place by offset (:class:`PlainTar`, ``os.pread``).
Another process (the DICOM decode processes of ``engine.io.procs``) cannot share those handles, so a member that
lies in a file of its own (a folder's file, a single file), in a zip or in an uncompressed tar also carries a
:class:`Where`: a small, picklable description from which :func:`read_where` reads the same bytes, with the same
checks and messages, in any process. A compressed tar's members, spooled to anonymous temporary files, have none.
"""

from __future__ import annotations

import os
import threading
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from engine.errors import InputError


@dataclass(frozen=True)
class Where:
    """Where one member's bytes lie, for a reader in another process.

    Attributes:
        kind: "zip" (``index`` in the archive's ``infolist()``), "tar" (``offset`` of the data in an uncompressed
            tar) or "file" (the whole file at ``path``).
        path: the archive or the file.
        name: the member's name (for messages, and to check that a zip still holds it at ``index``).
        size: its declared size in bytes.
        index: zip only.
        offset: tar only.
    """

    kind: str
    path: str
    name: str
    size: int
    index: int = -1
    offset: int = 0


def read_zip_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, archive_name: str) -> bytes:
    """One zip member's bytes: never more than its declared size (+1 to see a lie), CRC checked by zipfile.

    Raises:
        InputError: unreadable, corrupt, or not of its declared size.
    """
    try:
        with zf.open(info) as src:
            data = src.read(info.file_size + 1)
    except (zipfile.BadZipFile, NotImplementedError, RuntimeError, OSError, EOFError, ValueError) as exc:
        raise InputError(f"{archive_name}: member {info.filename!r} cannot be read: {exc}") from None
    if len(data) != info.file_size:
        raise InputError(
            f"archive member {info.filename!r} declares {info.file_size:,} bytes but holds "
            f"{'more' if len(data) > info.file_size else f'{len(data):,}'}: the archive is corrupt"
        )
    return data


def pread_member(fd: int, name: str, offset: int, size: int) -> bytes:
    """A tar member's bytes at ``offset``: exactly ``size`` of them, or InputError when the file ends first."""
    data = os.pread(fd, size, offset)
    if len(data) != size:
        raise InputError(
            f"archive member {name!r} declares {size:,} bytes but the archive ends after {len(data):,}: "
            "the archive is truncated"
        )
    return data


class ZipHandles:
    """One open ``ZipFile`` per reading thread over the same archive.

    A ``ZipFile`` keeps one file position and reference count for all its open members, which CPython does not
    promise to keep consistent under concurrent reads, so each thread that reads members gets a handle of its own
    (opening one re-reads the central directory: milliseconds). The listing's handle serves the thread that made it.
    """

    def __init__(self, path: Path, first: zipfile.ZipFile) -> None:
        self.path = path
        self._first, self._first_thread = first, threading.get_ident()
        self._local = threading.local()
        self._lock = threading.Lock()
        self._opened: list[zipfile.ZipFile] = [first]

    def get(self) -> zipfile.ZipFile:
        """The calling thread's handle."""
        if threading.get_ident() == self._first_thread:
            return self._first
        zf: zipfile.ZipFile | None = getattr(self._local, "zf", None)
        if zf is None:
            zf = zipfile.ZipFile(self.path)
            with self._lock:
                self._opened.append(zf)
            self._local.zf = zf
        return zf

    def reader(self, info: zipfile.ZipInfo) -> Callable[[], bytes]:
        """Reads one member through the calling thread's handle."""
        return lambda: read_zip_member(self.get(), info, self.path.name)

    def close(self) -> None:
        """Close every handle opened so far."""
        with self._lock:
            for zf in self._opened:
                zf.close()
            self._opened.clear()


class PlainTar:
    """An uncompressed tar read in place: each member's bytes sit at one offset of the file, so they are read with
    ``os.pread`` (no file position shared between threads) when a loader asks, and never copied to temporary files.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd: int | None = os.open(path, os.O_RDONLY)

    def reader(self, name: str, offset: int, size: int) -> Callable[[], bytes]:
        """Reads one member: exactly its declared size, or InputError when the file ends first."""

        def read() -> bytes:
            if self.fd is None:
                raise RuntimeError(f"{name}: the archive was closed")
            return pread_member(self.fd, name, offset, size)

        return read

    def close(self) -> None:
        """Close the file."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


_OPEN: list[tuple[tuple[object, ...], zipfile.ZipFile | int]] = []  # read_where's open archive (one at a time)
_OPEN_LOCK = threading.Lock()


def _handle(where: Where) -> zipfile.ZipFile | int:
    """This process's handle on ``where``'s archive: kept while the same file is read (a worker reads one archive
    member after member), closed when another archive, or a replaced file, is asked for."""
    st = os.stat(where.path)
    key = (where.kind, where.path, st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    with _OPEN_LOCK:
        if _OPEN and _OPEN[0][0] == key:
            return _OPEN[0][1]
        if _OPEN:
            old = _OPEN.pop()[1]
            if isinstance(old, int):
                os.close(old)
            else:
                old.close()
        handle: zipfile.ZipFile | int = (
            zipfile.ZipFile(where.path) if where.kind == "zip" else os.open(where.path, os.O_RDONLY)
        )
        _OPEN.append((key, handle))
        return handle


def read_where(where: Where) -> bytes:
    """A member's bytes from its :class:`Where`, in any process (meant for the decode processes: their handle on
    the archive is opened once and kept; see :func:`_handle`).

    Raises:
        InputError: as the in-process readers, or the archive no longer holds the member where it was listed.
    """
    if where.kind == "file":
        return Path(where.path).read_bytes()
    try:
        handle = _handle(where)
    except (OSError, zipfile.BadZipFile) as exc:
        raise InputError(f"{Path(where.path).name} cannot be read any more: {exc}") from None
    if isinstance(handle, int):
        return pread_member(handle, where.name, where.offset, where.size)
    infos = handle.infolist()
    info = infos[where.index] if 0 <= where.index < len(infos) else None
    if info is None or info.filename != where.name or info.file_size != where.size:
        raise InputError(f"{Path(where.path).name}: member {where.name!r} changed after the archive was listed")
    return read_zip_member(handle, info, Path(where.path).name)
