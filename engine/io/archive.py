"""Safe reading of the files inside a zip, a tar (optionally compressed), a folder or a single file.

Archive member names are only labels (for sorting and messages): nothing is ever written to disk under such a
name. Opening an input reads its listing and the first bytes of each member, and enforces the limits of
:class:`InputLimits` on the declared sizes: per member and for the whole archive, the total and the compression
ratio (so a bomb of many small, very compressible members is refused before anything is expanded). The bytes are
read later, one member at a time, when a loader asks for them: a zip member is decompressed straight from the
archive (never more than its declared size, so a header that lies is caught, not obeyed), through a handle of
the reading thread's own, so loaders may read members from several threads at once; an uncompressed tar's
members are read in place, by offset (``os.pread``); a compressed tar, which can only be read in order, is copied
into anonymous temporary files, in memory up to a small total, then on disk. The readers are in
``engine.io.readers``, with the :class:`~engine.io.readers.Where` that lets another process read a member that is
not spooled.
"""

from __future__ import annotations

import os
import re
import tarfile
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import IO

from engine.errors import InputError, NotAScanError
from engine.io.readers import PlainTar, Where, ZipHandles, read_where

_CHUNK = 1 << 20
_SPOOL_IN_MEMORY = 64 << 20  # all of a tar's members held in memory together; the rest go to temporary files
HEAD_BYTES = 132  # enough to see the DICOM preamble + "DICM" and every image signature
ZARR_MARKERS = ("zarr.json", ".zattrs", ".zgroup", ".zarray")  # the metadata files of a Zarr v3 / v2 node
_JUNK = re.compile(r"(^|/)(__MACOSX/|\.[^/]*$|Thumbs\.db$|desktop\.ini$)", re.IGNORECASE)


def is_junk(name: str) -> bool:
    """Whether a member's name is one every listing skips (``__MACOSX/``, hidden files, ``Thumbs.db``, ...)."""
    return _JUNK.search(name) is not None


@dataclass(frozen=True)
class InputLimits:
    """Ceilings that protect the engine from oversized or malicious input.

    Attributes:
        max_members: most entries (files, folders, links) an archive or folder may hold.
        max_total_bytes: most bytes all members may hold together once uncompressed.
        max_ratio: highest compression ratio (uncompressed / compressed) for one member and for the whole archive.
        ratio_floor_bytes: members (and archives) smaller than this uncompressed are not ratio-checked, so small,
            very regular files (e.g. an empty mask slice) do not trip the bomb check.
        max_voxels: most samples the loaded volume (after any resampling) may hold.
    """

    max_members: int = 20_000
    max_total_bytes: int = 8 << 30
    max_ratio: float = 200.0
    ratio_floor_bytes: int = 1 << 20
    max_voxels: int = 1 << 31

    def check_voxels(self, shape: tuple[int, ...], what: str) -> None:
        """Raise InputError when a volume of ``shape`` would exceed ``max_voxels``."""
        count = 1
        for n in shape:
            count *= int(n)
        if count > self.max_voxels:
            raise InputError(
                f"{what} would hold {count:,} voxels (shape {tuple(int(n) for n in shape)}), more than the limit of "
                f"{self.max_voxels:,}; crop or downsample the scan first"
            )


@dataclass
class Member:
    """One file of the input: its name (a label only), size and a way to read its bytes."""

    name: str
    size: int
    head: bytes
    _spool: IO[bytes] | None = field(default=None, repr=False)
    _path: Path | None = field(default=None, repr=False)
    _reader: Callable[[], bytes] | None = field(default=None, repr=False)
    where: Where | None = field(default=None, repr=False)  # for readers in other processes (engine.io.readers)

    @classmethod
    def at(cls, where: Where, head: bytes) -> Member:
        """The member that ``where`` locates, read from there (in any process: ``engine.io.readers.read_where``)."""
        return cls(where.name, where.size, head, _reader=partial(read_where, where), where=where)

    def read(self) -> bytes:
        """The member's whole content (not available in a ``heads_only`` listing of an archive).

        Raises:
            InputError: the member is corrupt or holds other than its declared size.
        """
        if self._reader is not None:
            return self._reader()
        if self._spool is not None:
            self._spool.seek(0)
            return self._spool.read()
        if self._path is not None:
            return self._path.read_bytes()
        raise RuntimeError(f"{self.name}: only the head of this member was read")


@dataclass
class Members:
    """The files of one input (use as a context manager: closing drops the temporary copies)."""

    kind: str
    members: list[Member]
    ignored: list[str] = field(default_factory=list)
    _archive: zipfile.ZipFile | ZipHandles | PlainTar | None = field(default=None, repr=False)

    def close(self) -> None:
        """Release the spooled copies and the open archive."""
        for m in self.members:
            if m._spool is not None:
                m._spool.close()
        if self._archive is not None:
            self._archive.close()

    def __enter__(self) -> Members:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_name(name: str, archive: Path) -> None:
    parts = re.split(r"[/\\]+", name)
    if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name) or ".." in parts:
        raise InputError(
            f"{archive.name} holds a member named {name!r} that points outside the archive (absolute path or '..'); "
            "refusing the archive: re-create it with relative member names"
        )


def _copy_limited(
    src: IO[bytes],
    name: str,
    declared: int,
    budget: _Budget,
    member_ratio_base: int | None,
    head_bytes: int = HEAD_BYTES,
) -> tuple[IO[bytes], int, bytes]:
    """Copy ``src`` into a temporary file (in memory while the archive's memory allowance lasts) while counting
    bytes against the limits."""
    in_memory = 0 <= declared <= budget.memory_left
    spool: IO[bytes] = tempfile.SpooledTemporaryFile(max_size=declared + 1) if in_memory else tempfile.TemporaryFile()
    if in_memory:
        budget.memory_left -= declared
    n = 0
    try:
        while chunk := src.read(_CHUNK):
            n += len(chunk)
            budget.add(len(chunk), name)
            lim = budget.limits
            if member_ratio_base is not None and n > lim.ratio_floor_bytes and n > lim.max_ratio * member_ratio_base:
                raise InputError(
                    f"archive member {name!r} expands more than {lim.max_ratio:g}x ({member_ratio_base:,} bytes "
                    f"compressed, over {n:,} bytes so far): this looks like a zip bomb; refusing it"
                )
            spool.write(chunk)
        if declared >= 0 and n != declared:
            raise InputError(
                f"archive member {name!r} declares {declared:,} bytes but holds {n:,}: the archive is corrupt"
            )
        spool.seek(0)
        head = spool.read(head_bytes)
    except BaseException:
        spool.close()
        raise
    return spool, n, head


class _Budget:
    """Running totals of one archive read."""

    def __init__(self, limits: InputLimits, archive: Path, compressed_size: int) -> None:
        self.limits = limits
        self.archive = archive
        self.compressed_size = max(compressed_size, 1)
        self.total = 0  # bytes actually expanded
        self.declared = 0  # bytes the members declare
        self.count = 0
        self.memory_left = _SPOOL_IN_MEMORY

    def entry(self) -> None:
        self.count += 1
        if self.count > self.limits.max_members:
            raise InputError(
                f"{self.archive.name} holds more than {self.limits.max_members:,} entries; expected one scan's slices "
                "(split the input or raise the member limit)"
            )

    def declare(self, name: str, size: int, compressed: int | None) -> None:
        lim = self.limits
        self.declared += size
        if self.declared > lim.max_total_bytes:
            raise InputError(
                f"{self.archive.name} would expand to more than {lim.max_total_bytes:,} bytes (at member {name!r}); "
                "refusing it as too large"
            )
        if self.declared > lim.ratio_floor_bytes and self.declared > lim.max_ratio * self.compressed_size:
            raise InputError(
                f"{self.archive.name} declares members of {self.declared:,} bytes so far (at member {name!r}) from "
                f"{self.compressed_size:,} bytes, more than {lim.max_ratio:g}x: this looks like a zip bomb; refusing it"
            )
        if compressed is not None and size > lim.ratio_floor_bytes and size > lim.max_ratio * max(compressed, 1):
            raise InputError(
                f"archive member {name!r} declares {size:,} bytes from {compressed:,} compressed (ratio over "
                f"{lim.max_ratio:g}): this looks like a zip bomb; refusing it"
            )

    def add(self, n: int, name: str) -> None:
        self.total += n
        lim = self.limits
        if self.total > lim.max_total_bytes:
            raise InputError(
                f"{self.archive.name} expands to more than {lim.max_total_bytes:,} bytes (at member {name!r}); "
                "refusing it as too large"
            )
        if self.total > lim.ratio_floor_bytes and self.total > lim.max_ratio * self.compressed_size:
            raise InputError(
                f"{self.archive.name} expands more than {lim.max_ratio:g}x its size of {self.compressed_size:,} bytes: "
                "this looks like a zip bomb; refusing it"
            )


def _head_only(
    src: IO[bytes], name: str, declared: int, budget: _Budget, head_bytes: int = HEAD_BYTES
) -> tuple[IO[bytes] | None, int, bytes]:
    """The first bytes of a member (for ``heads_only`` listings); the declared size stands for its size."""
    head = src.read(head_bytes)
    return None, max(declared, len(head)), head


def _read_zip(path: Path, limits: InputLimits, heads_only: bool = False, head_bytes: int = HEAD_BYTES) -> Members:
    budget = _Budget(limits, path, path.stat().st_size)
    members: list[Member] = []
    ignored: list[str] = []
    zf: zipfile.ZipFile | None = None
    handles: ZipHandles | None = None
    try:
        zf = zipfile.ZipFile(path)
        # the archive stays open for the members' readers; Members.close() closes it (and the readers' own)
        handles = ZipHandles(path, zf)
        infos = zf.infolist()
        if len(infos) > limits.max_members:
            raise InputError(
                f"{path.name} holds {len(infos):,} entries, more than the limit of {limits.max_members:,}; "
                "expected one scan's slices"
            )
        for index, info in enumerate(infos):
            budget.entry()
            _check_name(info.filename, path)
            if info.is_dir():
                continue
            if _JUNK.search(info.filename):
                ignored.append(info.filename)
                continue
            if info.flag_bits & 0x1:
                raise InputError(f"{path.name}: member {info.filename!r} is encrypted; give an unencrypted archive")
            budget.declare(info.filename, info.file_size, info.compress_size)
            with zf.open(info) as src:
                head = src.read(head_bytes)
            reader = None if heads_only else handles.reader(info)
            where = Where("zip", str(path), info.filename, info.file_size, index=index)
            members.append(Member(info.filename, max(info.file_size, len(head)), head, _reader=reader, where=where))
    except InputError:
        Members("zip", members, _archive=zf).close()
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, NotImplementedError, RuntimeError, OSError, EOFError) as exc:
        Members("zip", members, _archive=zf).close()
        raise NotAScanError(f"{path.name} is not a readable zip archive: {exc}") from None
    if heads_only:
        zf.close()
        return Members("zip", members, ignored)
    return Members("zip", members, ignored, _archive=handles)


def _read_tar(path: Path, limits: InputLimits, heads_only: bool = False, head_bytes: int = HEAD_BYTES) -> Members:
    budget = _Budget(limits, path, path.stat().st_size)
    members: list[Member] = []
    ignored: list[str] = []
    kind = "tar"
    plain: PlainTar | None = None  # an uncompressed tar is read in place; a compressed one is spooled
    try:
        with path.open("rb") as raw:
            magic = raw.read(6)
            raw.seek(0)
            kind = {b"\x1f\x8b": "tar.gz", b"BZ": "tar.bz2", b"\xfd7": "tar.xz"}.get(magic[:2], "tar")
            if kind == "tar" and not heads_only:
                plain = PlainTar(path)
            with tarfile.open(fileobj=raw, mode="r|*") as tf:
                for ti in tf:
                    budget.entry()
                    _check_name(ti.name, path)
                    if not ti.isfile():  # folders, symlinks, hard links, devices: never followed
                        if ti.issym() or ti.islnk():
                            ignored.append(ti.name)
                        continue
                    if _JUNK.search(ti.name):
                        ignored.append(ti.name)
                        continue
                    budget.declare(ti.name, ti.size, None)
                    src = tf.extractfile(ti)
                    assert src is not None
                    if heads_only:
                        spool, n, head = _head_only(src, ti.name, ti.size, budget, head_bytes)
                    elif plain is not None and not ti.issparse():  # read in place later, by offset
                        head = src.read(head_bytes)
                        budget.add(ti.size, ti.name)
                        reader = plain.reader(ti.name, ti.offset_data, ti.size)
                        where = Where("tar", str(path), ti.name, ti.size, offset=ti.offset_data)
                        members.append(Member(ti.name, ti.size, head, _reader=reader, where=where))
                        continue
                    else:
                        spool, n, head = _copy_limited(src, ti.name, ti.size, budget, None, head_bytes)
                    members.append(Member(ti.name, n, head, _spool=spool))
    except InputError:
        Members(kind, members, _archive=plain).close()
        raise
    except (tarfile.TarError, OSError, EOFError, ValueError) as exc:
        Members(kind, members, _archive=plain).close()
        raise NotAScanError(f"{path.name} is not a readable {kind} archive: {exc}") from None
    return Members(kind, members, ignored, _archive=plain)


def _read_folder(path: Path, limits: InputLimits, head_bytes: int = HEAD_BYTES) -> Members:
    members: list[Member] = []
    ignored: list[str] = []
    total = 0
    count = 0
    for root, dirs, files in os.walk(path, followlinks=False):
        dirs.sort()
        for zarr_dir in [d for d in dirs if is_zarr_folder(Path(root) / d)]:  # its metadata only, not its chunks
            dirs.remove(zarr_dir)
            top = _zarr_top(Path(root) / zarr_dir, head_bytes)
            assert top is not None
            meta = top.members[0]
            meta.name = (Path(root) / zarr_dir).relative_to(path).joinpath(meta.name).as_posix()
            members.append(meta)
        for fname in sorted(files):
            count += 1
            if count > limits.max_members:
                raise InputError(
                    f"folder {path} holds more than {limits.max_members:,} files; expected one scan's slices"
                )
            full = Path(root) / fname
            rel = full.relative_to(path).as_posix()
            if full.is_symlink() or not full.is_file() or _JUNK.search(rel):
                ignored.append(rel)
                continue
            size = full.stat().st_size
            total += size
            if total > limits.max_total_bytes:
                raise InputError(
                    f"folder {path} holds more than {limits.max_total_bytes:,} bytes; refusing it as too large"
                )
            with full.open("rb") as fh:
                head = fh.read(head_bytes)
            members.append(Member(rel, size, head, _path=full, where=Where("file", str(full), rel, size)))
    return Members("folder", members, ignored)


def open_members(
    path: str | Path, limits: InputLimits | None = None, *, heads_only: bool = False, head_bytes: int = HEAD_BYTES
) -> Members:
    """List the files of an input: a zip, tar(.gz/.bz2/.xz), a folder, or one plain file.

    With ``heads_only`` the members of an archive keep only their first bytes (``Member.head``; ``read`` is not
    available) and sizes are the declared ones: a quick listing that checks names, counts and declared sizes and
    ratios but not the bytes actually decompressed. ``head_bytes``: how many first bytes each member keeps (more
    than the default to tell a file's kind by content, e.g. a DICOM SEG by its file meta).

    Raises:
        InputError: the path is missing, or a corrupt archive, or an archive/folder beyond ``limits``.
    """
    limits = limits or InputLimits()
    path = Path(path)
    if path.is_dir():
        if (top := _zarr_top(path, head_bytes)) is not None:
            return top  # a Zarr hierarchy (engine.io.omezarr) is opened by zarr, not listed chunk by chunk
        return _read_folder(path, limits, head_bytes)
    if not path.is_file():
        raise InputError(f"{path} does not exist (expected a zip/tar archive, a folder, or a volume file)")
    if zipfile.is_zipfile(path):
        return _read_zip(path, limits, heads_only, head_bytes)
    name = path.name.lower()
    if name.endswith(".zip"):
        raise NotAScanError(f"{path.name} ends in .zip but is not a readable zip archive (corrupt or truncated?)")
    if _is_tar(path):
        return _read_tar(path, limits, heads_only, head_bytes)
    if name.endswith((".tar", ".tgz", ".tar.gz", ".tar.bz2", ".tar.xz")):
        raise InputError(
            f"{path.name} looks like a tar archive by name but cannot be read as one (corrupt or truncated?)"
        )
    size = path.stat().st_size
    if size > limits.max_total_bytes:
        raise InputError(f"{path.name} holds {size:,} bytes, more than the limit of {limits.max_total_bytes:,}")
    with path.open("rb") as fh:
        head = fh.read(head_bytes)
    return Members("file", [Member(path.name, size, head, _path=path, where=Where("file", str(path), path.name, size))])


def is_zarr_folder(path: Path) -> bool:
    """Whether the folder is a Zarr node itself (a group or an array: ``zarr.json``, ``.zattrs``, ``.zgroup`` or
    ``.zarray`` at its top), which ``engine.io.omezarr`` opens with zarr instead of listing it file by file."""
    return any((path / name).is_file() for name in ZARR_MARKERS)


def _zarr_top(path: Path, head_bytes: int) -> Members | None:
    """A folder that is a Zarr node (:func:`is_zarr_folder`) as kind "ome-zarr" with its metadata file as the one
    member (the label-map sniffer reads its head); None for any other folder."""
    if not is_zarr_folder(path):
        return None
    meta = next(p for p in (path / n for n in ZARR_MARKERS) if p.is_file())
    with meta.open("rb") as fh:
        head = fh.read(head_bytes)
    size = meta.stat().st_size
    return Members(
        "ome-zarr", [Member(meta.name, size, head, _path=meta, where=Where("file", str(meta), meta.name, size))]
    )


def _is_tar(path: Path) -> bool:
    try:
        return tarfile.is_tarfile(path)
    except (OSError, EOFError, tarfile.TarError):
        return False
