"""Where uploads and results live. ``Storage`` is the interface (a local folder here; S3-compatible storage can
implement it later); ``LocalStorage`` keeps ``jobs/<id>/upload`` and ``jobs/<id>/outputs/`` under one root.

Nothing is ever visible half-written: uploads stream into a temporary name and are renamed when complete; a
job's outputs are staged in a temporary folder and moved into place in one rename. The outputs a job may have are
the files of the registry ``engine.export.files.FILES`` (their kinds and media types are there too); only those
names are served.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import sqlite3
import uuid
from abc import ABC, abstractmethod
from pathlib import Path

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

    @abstractmethod
    def commit(self) -> None:
        """Make the upload the job's upload."""

    @abstractmethod
    def abort(self) -> None:
        """Drop what was written."""


class Storage(ABC):
    """Job files: one upload and a set of outputs per job."""

    @abstractmethod
    def upload_writer(self, job_id: str, max_bytes: int) -> UploadWriter:
        """A writer that streams an upload in, never holding it whole in memory."""

    @abstractmethod
    def upload_path(self, job_id: str) -> Path:
        """A local path of the upload (for the loader)."""

    @abstractmethod
    def staging_dir(self, job_id: str) -> Path:
        """A fresh private folder to write outputs into before ``publish``."""

    @abstractmethod
    def clean_staging(self, job_id: str) -> int:
        """Remove what earlier attempts at a job left (staging folders, replaced outputs); returns how many."""

    @abstractmethod
    def publish(self, job_id: str, staged: Path) -> None:
        """Make the staged outputs the job's outputs, at once (replacing any earlier set)."""

    @abstractmethod
    def output_path(self, job_id: str, name: str) -> Path | None:
        """A published output file, or None (also for a name that is no output file: ``FILES``)."""

    @abstractmethod
    def delete_job(self, job_id: str) -> None:
        """Remove the upload and every output of a job."""

    @abstractmethod
    def ping(self) -> None:
        """Raise when the storage cannot be written."""

    @abstractmethod
    def free_bytes(self) -> int | None:
        """Bytes still free for uploads, or None when unknown."""


class LocalStorage(Storage):
    """Job files in a folder on local disk."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        (self.root / "jobs").mkdir(parents=True, exist_ok=True)

    def _job(self, job_id: str) -> Path:
        if not _ID.match(job_id):
            raise ValueError(f"not a job id: {job_id!r}")
        return self.root / "jobs" / job_id

    def upload_writer(self, job_id: str, max_bytes: int) -> UploadWriter:
        return _LocalUpload(self._job(job_id), max_bytes)

    def upload_path(self, job_id: str) -> Path:
        return self._job(job_id) / "upload"

    def staging_dir(self, job_id: str) -> Path:
        folder = self._job(job_id) / f".staging-{uuid.uuid4().hex}"
        folder.mkdir(parents=True)
        return folder

    def clean_staging(self, job_id: str) -> int:
        folder = self._job(job_id)
        if not folder.is_dir():
            return 0
        left = [p for p in folder.iterdir() if p.name.startswith((".staging-", ".old-")) and p.is_dir()]
        for path in left:
            shutil.rmtree(path, ignore_errors=True)
        return len(left)

    def publish(self, job_id: str, staged: Path) -> None:
        final = self._job(job_id) / "outputs"
        old = self._job(job_id) / f".old-{uuid.uuid4().hex}"
        if final.exists():
            os.replace(final, old)
        os.replace(staged, final)
        shutil.rmtree(old, ignore_errors=True)

    def output_path(self, job_id: str, name: str) -> Path | None:
        if name not in FILES:  # the registry's names only: never a path of the caller's making
            return None
        path = self._job(job_id) / "outputs" / name
        return path if path.is_file() else None

    def delete_job(self, job_id: str) -> None:
        shutil.rmtree(self._job(job_id), ignore_errors=True)

    def ping(self) -> None:
        probe = self.root / f".ping-{uuid.uuid4().hex}"
        probe.write_bytes(b"ok")
        probe.unlink()

    def free_bytes(self) -> int | None:
        try:
            return shutil.disk_usage(self.root).free
        except OSError:
            return None


class _LocalUpload(UploadWriter):
    def __init__(self, folder: Path, max_bytes: int) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.max_bytes = max_bytes
        self.size = 0
        self.tmp = folder / f".upload-{uuid.uuid4().hex}.part"
        self.fh = self.tmp.open("wb")

    def write(self, chunk: bytes | memoryview) -> None:
        self.size += len(chunk)
        if self.size > self.max_bytes:
            self.abort()
            raise UploadTooLarge(f"the upload is larger than the limit of {self.max_bytes:,} bytes")
        self.fh.write(chunk)

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


def storage_from_settings(data_dir: Path) -> Storage:
    """The storage of the settings (local disk under the data folder)."""
    return LocalStorage(data_dir)
