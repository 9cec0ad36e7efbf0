"""Where uploads and results live. ``Storage`` is the interface, with two backends: ``LocalStorage`` (a folder:
``jobs/<id>/upload`` and ``jobs/<id>/outputs/`` under one root; the default) and ``core.s3storage.S3Storage`` (any
S3-compatible store; ``BONEMESH_STORAGE_URL=s3://bucket/prefix``). ``storage_from_settings`` picks one.

Nothing is ever visible half-written: uploads stream into a temporary name (a multipart upload on S3) and become
the job's upload when complete; a job's outputs are staged in a private local folder and published as one
*version* (``publish`` returns it). The worker records that version with the outputs in the job's row, and that
database commit is what makes them visible: readers ask for the recorded version (``version_of(job)``); on local
disk the version's folder is also moved into place in one rename. The outputs a job may have are the files of the
registry ``engine.export.files.FILES`` (their kinds and media types are there too); only those names are served.

Consumers never need a shared disk: the worker takes its input through ``local_upload`` (in place on local disk, a
scratch copy from S3, removed afterwards) and gives its outputs back through ``publish``.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime as dt
import errno
import functools
import os
import re
import shutil
import sqlite3
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from engine.export.files import FILES

_ID = re.compile(r"^[0-9a-f]{32}$")


_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


class UploadTooLarge(Exception):
    """The upload went over the byte limit (nothing was kept)."""


def is_storage_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) says the disk, the quota or the file size limit is exhausted: an OSError
    with ENOSPC, EDQUOT or EFBIG, or SQLite's SQLITE_FULL (as raised, or wrapped by SQLAlchemy)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, OSError) and cur.errno in _FULL_ERRNOS:
            return True
        if isinstance(cur, sqlite3.Error) and getattr(cur, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL:
            return True
        cur = getattr(cur, "orig", None) or cur.__cause__ or cur.__context__
    return False


class UploadWriter(ABC):
    """An upload being streamed in: ``write`` chunks, then ``commit`` (or ``abort``, which keeps nothing)."""

    size: int

    @abstractmethod
    def write(self, chunk: bytes | memoryview) -> None:
        """Append; raises UploadTooLarge past the limit."""

    def write_many(self, chunks: list[memoryview]) -> None:
        """Append each in order (one call for a batch of received buffers)."""
        for chunk in chunks:
            self.write(chunk)

    def local_part(self) -> Path | None:
        """The local file the upload is written to until ``commit`` (its first ``size`` bytes there after
        ``flush``), or None where there is none (S3)."""
        return None

    def flush(self) -> None:
        """Hand what ``write`` took to the file (``local_part``)."""
        return None

    @abstractmethod
    def commit(self) -> None:
        """Make the upload the job's upload."""

    @abstractmethod
    def abort(self) -> None:
        """Drop what was written."""


@dataclass(frozen=True)
class StoredFile:
    """A published output: its size, a validator (changes whenever the bytes may have) and, on local disk, its
    path."""

    name: str
    size: int
    tag: str
    path: Path | None = None


def version_of(job: Any) -> str | None:
    """The output version recorded with a job's outputs (``publish``'s answer, committed by the worker), or None
    (a job recorded before versions, or one without outputs)."""
    for entry in getattr(job, "outputs", None) or []:
        if entry.get("version"):
            return str(entry["version"])
    return None


_JOB_PATH = re.compile(r"(?:[A-Za-z]:)?[/\\][^\s'\"]*?[/\\]jobs[/\\][0-9a-f]{32}(?:[/\\][^\s'\":,;)]*)?")


def scrub_paths(message: str, labels: dict[str, str] | None = None) -> str:
    """``message`` with server paths hidden: each key of ``labels`` (a local path: the upload's, a staging
    folder's) written as its value, longest first, then any path left inside a job's folder as "the job's files"."""
    for path, label in sorted((labels or {}).items(), key=lambda kv: -len(kv[0])):
        if path:
            message = message.replace(path, label)
    return _JOB_PATH.sub("the job's files", message)


@dataclass(frozen=True)
class PartLink:
    """Where to send one part of a direct upload: ``PUT url`` with exactly ``headers`` (the only headers signed
    besides Host; any other header the client's library adds, Content-Type included, is not signed and harmless)."""

    number: int
    url: str
    headers: dict[str, str]


@dataclass(frozen=True)
class StoredPart:
    """A part the store holds of a direct upload not yet completed."""

    number: int
    etag: str
    size: int


class DirectUploads(ABC):
    """Uploads sent by the client straight to the store (``Storage.direct``; S3 only): a multipart upload of a
    job's upload key whose parts the client PUTs through presigned links; completing it makes it the job's upload,
    aborting it keeps nothing."""

    @abstractmethod
    def begin(self, job_id: str) -> str:
        """Start the multipart upload of the job's upload; returns the store's upload id."""

    @abstractmethod
    def part_links(self, job_id: str, upload_id: str, count: int, ttl_seconds: int) -> list[PartLink]:
        """Presigned (SigV4) ``UploadPart`` links of parts 1..count, valid ``ttl_seconds``."""

    @abstractmethod
    def parts(self, job_id: str, upload_id: str) -> list[StoredPart]:
        """The parts received so far, by number (FileNotFoundError when the upload is gone)."""

    @abstractmethod
    def complete(self, job_id: str, upload_id: str, parts: list[tuple[int, str]]) -> None:
        """Join the parts (number, ETag) into the job's upload (ValueError when the store refuses them)."""

    @abstractmethod
    def abort(self, job_id: str, upload_id: str) -> None:
        """Drop the upload and every part received (no error when it is gone already)."""

    @abstractmethod
    def pending(self, started_before: Any) -> list[tuple[str, str]]:
        """(job id, upload id) of the multipart uploads of job uploads begun before ``started_before`` (an aware
        datetime), neither completed nor aborted, and with no part received since."""


class Storage(ABC):
    """Job files: one upload and a set of outputs per job."""

    #: the store's own presigned download links are available (``output_url``)
    presigns = False
    #: clients may upload straight to the store (S3); None on local disk (the upload goes through the API)
    direct: DirectUploads | None = None

    @abstractmethod
    def upload_writer(self, job_id: str, max_bytes: int) -> UploadWriter:
        """A writer that streams an upload in, never holding it whole in memory."""

    @abstractmethod
    def put_upload_folder(self, job_id: str, folder: Path) -> contextlib.AbstractContextManager[None]:
        """Make a local folder (a DICOM series received by the PACS gateway) the job's upload for the ``with``
        block: kept when the block succeeds (the folder is then gone: moved, or copied and removed), given back
        into ``folder`` when it raises (nothing of it left in the store)."""

    @abstractmethod
    def has_upload(self, job_id: str) -> bool:
        """Whether the job has a complete upload."""

    @abstractmethod
    def local_upload(self, job_id: str) -> contextlib.AbstractContextManager[Path]:
        """A local path of the upload for the time of the ``with`` block (a scratch copy where the store is not
        local, removed on leaving, also on failure). The path may not exist (no upload: the loader says so)."""

    @abstractmethod
    def inspect_path(self, job_id: str) -> contextlib.AbstractContextManager[Path]:
        """A local path of a just-committed upload for the API's checks (``service.upload_check``)."""

    def predecode_path(self, job_id: str) -> Path | None:
        """Where an upload streaming in is: the API decodes its slices beside it as they arrive
        (``engine.io.predecode``) and the worker finds them there. None where the store is not local disk: the
        decoded volume is about twice the zip, and sending it to the store and back costs more than decoding."""
        return None

    @abstractmethod
    def staging_dir(self, job_id: str) -> Path:
        """A fresh private local folder to write outputs into before ``publish``."""

    def drop_staging(self, staged: Path) -> None:
        """Remove a staging folder that will not be published."""
        shutil.rmtree(staged, ignore_errors=True)

    @abstractmethod
    def clean_staging(self, job_id: str) -> int:
        """Remove what earlier attempts at a job left (staging folders, replaced outputs, a killed fetch's partial
        series); returns how many."""

    @abstractmethod
    def publish(self, job_id: str, staged: Path) -> str:
        """Store the staged outputs as a new version of the job's outputs and return the version; the staged
        folder is consumed. The caller records the version with the outputs (one database commit): that makes
        them the job's outputs."""

    def retire(self, job_id: str, keep: str) -> None:
        """Remove every output version of a job but ``keep`` (after its commit; also what killed attempts left,
        their unfinished multipart uploads included). Local disk keeps one version in place: nothing to do."""
        return None

    def sweep_outputs(self, started_before: dt.datetime) -> int:
        """Remove what publishes killed half way left before ``started_before`` (an S3 store's unfinished
        multipart uploads of outputs, local disk's replaced output folders); returns how many. The API's
        background sweep calls it."""
        return 0

    @abstractmethod
    def output(self, job_id: str, name: str, version: str | None = None) -> StoredFile | None:
        """A published output, or None (also for a name that is no output file: ``FILES``)."""

    @abstractmethod
    def read_output(self, job_id: str, name: str, version: str | None = None) -> bytes | None:
        """A (small) published output's bytes, or None."""

    @abstractmethod
    def open_output(self, job_id: str, name: str, version: str | None = None) -> Iterator[bytes]:
        """A published output's bytes, in chunks (FileNotFoundError when gone)."""

    @abstractmethod
    def local_output(
        self, job_id: str, name: str, version: str | None = None
    ) -> contextlib.AbstractContextManager[Path | None]:
        """A local path of a published output for the ``with`` block (a scratch copy off local disk), or None."""

    @abstractmethod
    def copy_outputs(self, job_id: str, version: str | None, into: Path) -> list[str]:
        """Copy every published output of ``version`` into the local folder ``into``; returns their names."""

    def output_url(self, job_id: str, name: str, version: str | None, ttl_seconds: int) -> str | None:
        """The store's own presigned download link (None where there is none: local disk)."""
        return None

    @abstractmethod
    def delete_job(self, job_id: str) -> None:
        """Remove the upload and every output of a job."""

    @abstractmethod
    def ping(self) -> None:
        """Raise when the storage cannot be written."""

    @abstractmethod
    def free_bytes(self) -> int | None:
        """Bytes still free for uploads, or None when unknown."""

    def local_paths(self, job_id: str) -> dict[str, str]:
        """Local paths of a job this storage may put in a message, with the words to show instead."""
        return {}


def check_job_id(job_id: str) -> str:
    if not _ID.match(job_id):
        raise ValueError(f"not a job id: {job_id!r}")
    return job_id


def output_name_ok(name: str) -> bool:
    """Only the registry's names: never a path of the caller's making."""
    return name in FILES


class LocalStorage(Storage):
    """Job files in a folder on local disk (the version of the outputs in place is the one in ``outputs/.version``)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        (self.root / "jobs").mkdir(parents=True, exist_ok=True)

    def _job(self, job_id: str) -> Path:
        return self.root / "jobs" / check_job_id(job_id)

    def upload_writer(self, job_id: str, max_bytes: int) -> UploadWriter:
        return _LocalUpload(self._job(job_id), max_bytes)

    @contextlib.contextmanager
    def put_upload_folder(self, job_id: str, folder: Path) -> Iterator[None]:
        upload = self.upload_path(job_id)
        upload.parent.mkdir(parents=True, exist_ok=True)
        os.replace(folder, upload)
        try:
            yield
        except BaseException:
            os.replace(upload, folder)
            raise

    def has_upload(self, job_id: str) -> bool:
        return self.upload_path(job_id).exists()

    def upload_path(self, job_id: str) -> Path:
        """The upload's path (local disk only)."""
        return self._job(job_id) / "upload"

    @contextlib.contextmanager
    def local_upload(self, job_id: str) -> Iterator[Path]:
        yield self.upload_path(job_id)

    def inspect_path(self, job_id: str) -> contextlib.AbstractContextManager[Path]:
        return self.local_upload(job_id)

    def predecode_path(self, job_id: str) -> Path | None:
        return self.upload_path(job_id)

    def staging_dir(self, job_id: str) -> Path:
        folder = self._job(job_id) / f".staging-{uuid.uuid4().hex}"
        folder.mkdir(parents=True)
        return folder

    def clean_staging(self, job_id: str) -> int:
        folder = self._job(job_id)
        if not folder.is_dir():
            return 0
        # staging folders, replaced outputs, and the partial series of a DICOMweb fetch killed midway (worker.pacs)
        left = [p for p in folder.iterdir() if p.name.startswith((".staging-", ".old-", ".fetch-")) and p.is_dir()]
        for path in left:
            shutil.rmtree(path, ignore_errors=True)
        return len(left)

    def publish(self, job_id: str, staged: Path) -> str:
        version = uuid.uuid4().hex
        (staged / ".version").write_text(version)
        final = self._job(job_id) / "outputs"
        old = self._job(job_id) / f".old-{uuid.uuid4().hex}"
        if final.exists():
            os.replace(final, old)
        os.replace(staged, final)
        shutil.rmtree(old, ignore_errors=True)
        return version

    def output_path(self, job_id: str, name: str) -> Path | None:
        """A published output's path (local disk only), or None."""
        if not output_name_ok(name):
            return None
        path = self._job(job_id) / "outputs" / name
        return path if path.is_file() else None

    def output(self, job_id: str, name: str, version: str | None = None) -> StoredFile | None:
        path = self.output_path(job_id, name)
        if path is None:
            return None
        st = path.stat()
        return StoredFile(name, st.st_size, f"{st.st_mtime_ns}/{st.st_size}", path)

    def read_output(self, job_id: str, name: str, version: str | None = None) -> bytes | None:
        path = self.output_path(job_id, name)
        return path.read_bytes() if path is not None else None

    def open_output(self, job_id: str, name: str, version: str | None = None) -> Iterator[bytes]:
        path = self.output_path(job_id, name)
        if path is None:
            raise FileNotFoundError(name)
        with open(path, "rb") as fh:
            while chunk := fh.read(1 << 20):
                yield chunk

    @contextlib.contextmanager
    def local_output(self, job_id: str, name: str, version: str | None = None) -> Iterator[Path | None]:
        yield self.output_path(job_id, name)

    def copy_outputs(self, job_id: str, version: str | None, into: Path) -> list[str]:
        names = []
        for path in (self._job(job_id) / "outputs").iterdir():
            if path.is_file() and output_name_ok(path.name):
                shutil.copy2(path, into / path.name)
                names.append(path.name)
        return names

    def delete_job(self, job_id: str) -> None:
        shutil.rmtree(self._job(job_id), ignore_errors=True)

    def sweep_outputs(self, started_before: dt.datetime) -> int:
        gone = 0
        for old in (self.root / "jobs").glob("*/.old-*"):  # a publish killed between its two renames
            with contextlib.suppress(OSError):
                if dt.datetime.fromtimestamp(old.stat().st_mtime, dt.UTC) < started_before:
                    shutil.rmtree(old)
                    gone += 1
        return gone

    def ping(self) -> None:
        probe = self.root / f".ping-{uuid.uuid4().hex}"
        probe.write_bytes(b"ok")
        probe.unlink()

    def free_bytes(self) -> int | None:
        try:
            return shutil.disk_usage(self.root).free
        except OSError:
            return None

    def local_paths(self, job_id: str) -> dict[str, str]:
        return {str(self.upload_path(job_id)): "upload", str(self._job(job_id)): "the job's files"}


WRITEBACK_BYTES = 64 << 20  # an upload's bytes are handed to the disk every this many (``start_writeback``)
_SYNC_FILE_RANGE_WRITE = 2  # Linux's SYNC_FILE_RANGE_WRITE: start writing the range's dirty pages, do not wait


@functools.cache
def _sync_file_range() -> Any:
    """libc's ``sync_file_range`` (Linux), or None where there is none."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).sync_file_range
    except (OSError, AttributeError):
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint)
    fn.restype = ctypes.c_int
    return fn


def start_writeback(fd: int, offset: int, length: int) -> None:
    """Start writing a file's range to the disk without waiting for it (Linux; elsewhere nothing), so that the
    fsync that makes an upload durable waits for its last range only, not for the whole file: the kernel would
    otherwise hold a 1 GB upload in memory until that fsync."""
    fn = _sync_file_range()
    if fn is not None:
        fn(fd, offset, length, _SYNC_FILE_RANGE_WRITE)  # a failure here leaves it to the fsync, which reports it


def write_all(fd: int, chunks: list[memoryview]) -> None:
    """Write the buffers to ``fd`` in order with as few ``writev`` calls as the system allows (a short write goes
    on from where it stopped)."""
    left = [memoryview(c).cast("B") for c in chunks if len(c)]
    try:
        most = os.sysconf("SC_IOV_MAX")
    except (AttributeError, ValueError, OSError):
        most = 16  # POSIX's least
    most = most if most > 0 else 1024  # -1: the system names no limit
    while left:
        done = os.writev(fd, left[:most])
        while done and left:
            if done >= len(left[0]):
                done -= len(left.pop(0))
            else:
                left[0], done = left[0][done:], 0


class _LocalUpload(UploadWriter):
    def __init__(self, folder: Path, max_bytes: int) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.max_bytes = max_bytes
        self.size = 0
        self.written_back = 0  # bytes handed to the disk so far (``start_writeback``)
        self.tmp = folder / f".upload-{uuid.uuid4().hex}.part"
        self.fh = self.tmp.open("wb")

    def write(self, chunk: bytes | memoryview) -> None:
        self._grow(len(chunk))
        self.fh.write(chunk)
        self._hand_over()

    def write_many(self, chunks: list[memoryview]) -> None:
        """One ``writev`` per batch instead of a ``write`` per received buffer (a batch is 64 of them): the thread
        that writes gives the API's event loop the interpreter back once per batch, not once per 64 KiB."""
        self._grow(sum(len(c) for c in chunks))
        self.fh.flush()  # what ``write`` left in the file object's buffer goes first
        write_all(self.fh.fileno(), chunks)
        self._hand_over()

    def _grow(self, n: int) -> None:
        """Count ``n`` more bytes; past the limit, nothing is kept (UploadTooLarge)."""
        self.size += n
        if self.size > self.max_bytes:
            self.abort()
            raise UploadTooLarge(f"the upload is larger than the limit of {self.max_bytes:,} bytes")

    def _hand_over(self) -> None:
        """Every ``WRITEBACK_BYTES``, the bytes written since start on their way to the disk."""
        if self.size - self.written_back >= WRITEBACK_BYTES:
            self.fh.flush()
            start_writeback(self.fh.fileno(), self.written_back, self.size - self.written_back)
            self.written_back = self.size

    def local_part(self) -> Path | None:
        return self.tmp

    def flush(self) -> None:
        self.fh.flush()

    def commit(self) -> None:
        self.fh.flush()
        os.fsync(self.fh.fileno())
        self.fh.close()
        os.replace(self.tmp, self.folder / "upload")

    def abort(self) -> None:
        try:
            self.fh.close()  # flushes: on a full disk that fails too, and the file goes all the same
        except OSError:
            pass
        finally:
            self.tmp.unlink(missing_ok=True)


def storage_from_settings(settings: Any) -> Storage:
    """The storage of the settings: ``BONEMESH_STORAGE_URL`` (``file:///path``, default the data folder, or
    ``s3://bucket/prefix``; core.s3storage). A bare data folder (older callers) means local disk there."""
    if isinstance(settings, str | Path):
        return LocalStorage(settings)
    kind, where = settings.storage_location()
    if kind == "s3":
        from core.s3storage import S3Storage

        bucket, _, prefix = where.partition("/")
        return S3Storage(bucket, prefix, endpoint_url=settings.s3_endpoint_url, scratch=settings.scratch_root())
    return LocalStorage(where)


def scrub_exception(exc: BaseException, labels: dict[str, str]) -> BaseException:
    """``exc`` with the server paths in its message hidden (``scrub_paths``), for messages made from it."""
    if len(exc.args) == 1 and isinstance(exc.args[0], str):
        exc.args = (scrub_paths(exc.args[0], labels),)
    return exc
