"""A zip archive read front to back as its bytes arrive: each member's bytes as soon as they are all there.

A zip's members follow one another, each behind its local header, and its central directory comes last.
:class:`ZipStream` is fed the archive's bytes in order (any chunking) and gives back every member completed by them
(:class:`ZipEntry`: its name, where its local header starts, its CRC and sizes, its bytes as stored). It follows
stored and deflated members, members whose sizes come after their data (a data descriptor, bit 3: a deflated one
is inflated to find its end; a stored one ends where a descriptor's CRC and size match the bytes before it), and
zip64 sizes (the local header's zip64 extra field). It stops at the central directory (``ended``).

What it does not follow (an encrypted member, another compression method, bytes before the first local header
such as a self-extracting stub, a member over ``max_member_bytes``) raises :class:`CannotStream`: the caller then
reads the archive whole, as before. Nothing here is trusted on its own: the caller checks the entries against the
central directory of the complete archive (``engine.io.predecode``).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

__all__ = ["CannotStream", "ZipEntry", "ZipStream"]

LOCAL = b"PK\x03\x04"
DESCRIPTOR = b"PK\x07\x08"
ENDS = (b"PK\x01\x02", b"PK\x05\x06", b"PK\x06\x06")  # the central directory, the end records
_HEADER = struct.Struct("<4sHHHHHIIIHH")  # signature, version, flags, method, time, date, crc, sizes, name, extra
MAX_MEMBER_BYTES = 512 << 20


class CannotStream(Exception):
    """The archive holds what a front-to-back reading does not follow (read it whole instead)."""


@dataclass(frozen=True)
class ZipEntry:
    """One member as its local header and data gave it. ``parts``: its bytes as stored (deflated for ``method``
    8), in pieces (views of the bytes fed: nothing is copied until ``content``), or already inflated where
    ``inflated`` (a deflated member with a data descriptor)."""

    name: str
    offset: int
    crc: int
    compress_size: int
    file_size: int
    method: int
    parts: tuple[bytes | memoryview, ...]
    inflated: bool = False

    @property
    def stored_bytes(self) -> int:
        """The bytes ``parts`` hold."""
        return sum(len(p) for p in self.parts)

    def head(self, n: int) -> bytes:
        """The member's first ``n`` bytes (fewer where it is shorter), inflated where it is deflated; what does not
        inflate gives what did."""
        first = bytes(self.parts[0][:n]) if self.parts else b""
        if len(first) < n and len(self.parts) > 1:
            first = b"".join(self.parts)[:n]
        if self.method != 8 or self.inflated:
            return first
        want, got = 4 * n + 64, 0  # a head's deflate stream is short
        pieces: list[bytes] = []
        for part in self.parts:
            pieces.append(bytes(part[: want - got]))
            got += len(pieces[-1])
            if got >= want:
                break
        try:
            return zlib.decompressobj(-15).decompress(b"".join(pieces), n)
        except zlib.error:
            return b""

    def content(self) -> bytes:
        """The member's bytes, joined (one copy, without the GIL for large members), inflated, their size and CRC
        checked.

        Raises:
            CannotStream: they do not inflate, or not to the declared size and CRC.
        """
        first = self.parts[0] if self.parts else b""
        data = first if len(self.parts) == 1 and isinstance(first, bytes) else b"".join(self.parts)
        if self.method == 8 and not self.inflated:
            d = zlib.decompressobj(-15)
            try:
                data = d.decompress(data, self.file_size + 1)
            except zlib.error as exc:
                raise CannotStream(f"{self.name}: {exc}") from None
        if len(data) != self.file_size or zlib.crc32(data) != self.crc:
            raise CannotStream(f"{self.name}: not the size or CRC its header declares")
        return data


class ZipStream:
    """Feed it the archive's bytes in order (``feed``); it returns the members each call completed.

    The data of a member whose size its local header gives are kept as views of the bytes fed (``ZipEntry.parts``:
    the caller's buffers must not change afterwards: bytes, or views of bytes); headers, descriptors and the data
    of members with a descriptor go through a small buffer of its own.
    """

    def __init__(self, max_member_bytes: int = MAX_MEMBER_BYTES) -> None:
        self.max_member_bytes = max_member_bytes
        self.buf = bytearray()
        self.at = 0  # the archive offset of buf[0]
        self.ended = False  # the central directory was reached
        self._cur: dict[str, int | str | bool] | None = None  # the member whose data is being read
        self._inflate: zlib._Decompress | None = None
        self._out: list[bytes] = []
        self._produced = 0
        self._consumed = 0
        self._crc, self._crc_at, self._scan_at = 0, 0, 0  # a stored member with a descriptor: its running CRC
        self._parts: list[bytes | memoryview] = []  # a member of known size: its data so far
        self._need = 0  # ... and the bytes still to come

    def feed(self, data: bytes | memoryview) -> list[ZipEntry]:
        """The members completed by ``data`` (the archive's next bytes).

        Raises:
            CannotStream: see the module docstring (the stream cannot be used any further).
        """
        view = memoryview(data)
        if view.ndim != 1 or view.itemsize != 1:
            view = view.cast("B")
        done: list[ZipEntry] = []
        while view and not self.ended:
            if self._known() and not self.buf:  # a member's data: kept as views, not copied
                k = min(self._need, len(view))
                self._parts.append(view[:k])
                self._need -= k
                self.at += k
                view = view[k:]
                if not self._need:
                    self._finish_known(done)
                continue
            self.buf += view
            view = view[:0]
            while not self.ended and self._step(done):
                pass
        return done

    def _known(self) -> bool:
        """Reading the data of a member whose size its header gave."""
        return self._cur is not None and not self._cur["descriptor"]

    def _finish_known(self, done: list[ZipEntry]) -> None:
        assert self._cur is not None
        parts, self._parts = tuple(self._parts), []
        self._emit(done, parts, int(self._cur["crc"]), int(self._cur["csize"]), int(self._cur["usize"]))

    def _take(self, n: int) -> bytes:
        with memoryview(self.buf) as view:
            out = bytes(view[:n])  # one copy
        del self.buf[:n]
        self.at += n
        return out

    def _step(self, done: list[ZipEntry]) -> bool:
        if self._cur is None:
            return self._header()
        if self._inflate is not None:
            return self._inflating(done)
        if self._cur["descriptor"]:
            return self._scanning(done)
        if self._need and self.buf:  # what the buffer holds of its data (after its header, fed with it)
            k = min(self._need, len(self.buf))
            self._parts.append(self._take(k))
            self._need -= k
        if self._need:
            return False  # the rest comes straight from feed
        self._finish_known(done)
        return True

    def _header(self) -> bool:
        if len(self.buf) < 4:
            return False
        sig = bytes(self.buf[:4])
        if sig in ENDS:
            self.ended = True
            self.buf.clear()
            return False
        if sig != LOCAL:
            raise CannotStream(f"no local header at offset {self.at}")
        if len(self.buf) < _HEADER.size:
            return False
        _, _, flags, method, _, _, crc, csize, usize, nlen, elen = _HEADER.unpack_from(self.buf)
        if len(self.buf) < _HEADER.size + nlen + elen:
            return False
        if flags & 0x1:
            raise CannotStream("an encrypted member")
        if method not in (0, 8):
            raise CannotStream(f"compression method {method}")
        raw = bytes(self.buf[_HEADER.size : _HEADER.size + nlen])
        extra = bytes(self.buf[_HEADER.size + nlen : _HEADER.size + nlen + elen])
        name = raw.decode("utf-8") if flags & 0x800 else raw.decode("cp437")
        zip64, usize, csize = _zip64(extra, usize, csize)
        offset = self.at
        self._take(_HEADER.size + nlen + elen)
        descriptor = bool(flags & 0x8)
        if not descriptor and max(csize, usize) > self.max_member_bytes:
            raise CannotStream(f"{name}: a member over {self.max_member_bytes:,} bytes")
        self._cur = {"name": name, "offset": offset, "method": method, "crc": crc, "csize": csize, "usize": usize,
                     "zip64": zip64, "descriptor": descriptor}  # fmt: skip
        if descriptor and method == 8:
            self._inflate, self._out, self._produced, self._consumed = zlib.decompressobj(-15), [], 0, 0
        self._parts, self._need = [], 0 if descriptor else csize
        self._crc, self._crc_at, self._scan_at = 0, 0, 0
        return True

    def _inflating(self, done: list[ZipEntry]) -> bool:
        """A deflated member with a descriptor: inflated as it comes, to find where its data end."""
        assert self._cur is not None and self._inflate is not None
        d = self._inflate
        if not d.eof:
            if not self.buf:
                return False
            chunk = self._take(len(self.buf))
            left = self.max_member_bytes - self._produced
            try:
                out = d.decompress(chunk, left + 1)
            except zlib.error as exc:
                raise CannotStream(f"{self._cur['name']}: {exc}") from None
            if len(out) > left or d.unconsumed_tail:
                raise CannotStream(f"{self._cur['name']}: a member over {self.max_member_bytes:,} bytes")
            self._out.append(out)
            self._produced += len(out)
            self._consumed += len(chunk) - len(d.unused_data)
            if d.eof:  # the bytes after the stream go back to the buffer
                self.buf[:0] = d.unused_data
                self.at -= len(d.unused_data)
            return True
        size = 24 if self._cur["zip64"] else 16  # with its signature
        if len(self.buf) < size:
            return False
        at = 4 if bytes(self.buf[:4]) == DESCRIPTOR else 0
        fmt = "<IQQ" if self._cur["zip64"] else "<III"
        crc, csize, usize = struct.unpack_from(fmt, self.buf, at)
        if csize != self._consumed or usize != self._produced:
            raise CannotStream(f"{self._cur['name']}: its data descriptor does not match its data")
        self._take(at + struct.calcsize(fmt))
        data = b"".join(self._out)
        self._inflate, self._out = None, []
        self._emit(done, (data,), crc, self._consumed, usize, inflated=True)
        return True

    def _scanning(self, done: list[ZipEntry]) -> bool:
        """A stored member with a descriptor: it ends at a descriptor whose size is the bytes before it and whose
        CRC is theirs."""
        assert self._cur is not None
        fmt = "<IQQ" if self._cur["zip64"] else "<III"
        need = 4 + struct.calcsize(fmt)
        while True:
            p = self.buf.find(DESCRIPTOR, self._scan_at)
            if p < 0:
                self._scan_at = max(0, len(self.buf) - 3)
                if len(self.buf) > self.max_member_bytes:
                    raise CannotStream(f"{self._cur['name']}: a member over {self.max_member_bytes:,} bytes")
                return False
            if len(self.buf) < p + need:
                self._scan_at = p
                return False
            crc, csize, usize = struct.unpack_from(fmt, self.buf, p + 4)
            if csize == usize == p:
                self._crc = zlib.crc32(memoryview(self.buf)[self._crc_at : p], self._crc)
                self._crc_at = p
                if crc == self._crc:
                    data = self._take(p)
                    self._take(need)
                    self._emit(done, (data,), crc, p, p)
                    return True
            self._scan_at = p + 1

    def _emit(
        self,
        done: list[ZipEntry],
        parts: tuple[bytes | memoryview, ...],
        crc: int,
        csize: int,
        usize: int,
        *,
        inflated: bool = False,
    ) -> None:
        cur = self._cur
        assert cur is not None
        name, offset, method = str(cur["name"]), int(cur["offset"]), int(cur["method"])
        done.append(ZipEntry(name, offset, crc, csize, usize, method, parts, inflated))
        self._cur = None


def _zip64(extra: bytes, usize: int, csize: int) -> tuple[bool, int, int]:
    """Whether the local header has a zip64 extra field, and the sizes it gives where the header's are 0xFFFFFFFF
    (the uncompressed size first, then the compressed one, each only where the header's is 0xFFFFFFFF)."""
    at = 0
    while at + 4 <= len(extra):
        kind, n = struct.unpack_from("<HH", extra, at)
        if kind == 0x0001:
            body, k = extra[at + 4 : at + 4 + n], 0
            if usize == 0xFFFFFFFF and k + 8 <= len(body):
                (usize,) = struct.unpack_from("<Q", body, k)
                k += 8
            if csize == 0xFFFFFFFF and k + 8 <= len(body):
                (csize,) = struct.unpack_from("<Q", body, k)
            return True, usize, csize
        at += 4 + n
    if 0xFFFFFFFF in (usize, csize):
        raise CannotStream("zip64 sizes without their extra field")
    return False, usize, csize
