"""Received instances on disk, grouped by study and series until the series is stable, then handed over whole.

Layout under ``<data_dir>/pacs``::

    incoming/<StudyInstanceUID>/<SeriesInstanceUID>/<SOPInstanceUID>.dcm   as they arrive
    incoming/<study>/<series>/.sender.json                                 who sent it (AE title, address)
    claimed/<random>/                                                      a stable series being turned into a job
    kept/<SeriesInstanceUID>/                                              a CT no rule took, kept for a later SEG

An instance is written to a temporary file first and renamed into its series folder under a lock, so the sweep
that claims a stable series (one rename, under the same lock) never takes a half-written file, and an instance
that arrives after the claim starts a new series folder (a new job: a re-sent series is never mixed into a job
that has started). Re-sending an instance (same SOP Instance UID) replaces the file: idempotent. A series is stable
when its folder has not changed for ``stable_seconds`` (the folder's mtime: restarts keep the clock).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from core.pacs.records import is_uid

SENDER = ".sender.json"


@dataclass(frozen=True)
class ClaimedSeries:
    """A stable series taken out of ``incoming``: its folder of instances and who sent it."""

    folder: Path
    study_uid: str
    series_uid: str
    sender: dict[str, Any]

    def files(self) -> list[Path]:
        """The instance files."""
        return sorted(p for p in self.folder.iterdir() if p.suffix == ".dcm")


class Inbox:
    """The incoming folder (see the module docstring).

    Args:
        root: ``<data_dir>/pacs``.
        stable_seconds: how long a series folder must stay unchanged to be complete.
    """

    def __init__(self, root: Path, stable_seconds: float) -> None:
        self.root = Path(root)
        self.incoming = self.root / "incoming"
        self.claimed = self.root / "claimed"
        self.kept = self.root / "kept"
        self.tmp = self.root / "tmp"
        for folder in (self.incoming, self.claimed, self.kept, self.tmp):
            folder.mkdir(parents=True, exist_ok=True)
        self.stable_seconds = stable_seconds
        self._lock = threading.Lock()

    def store(
        self, study_uid: str, series_uid: str, sop_uid: str, sender: dict[str, Any], write: Callable[[BinaryIO], None]
    ) -> bool:
        """Write one instance with ``write(fh)`` into its series folder; True when it replaced an earlier copy.

        Raises:
            ValueError: a UID is malformed (it would not be a safe file name either).
        """
        for uid in (study_uid, series_uid, sop_uid):
            if not is_uid(uid):
                raise ValueError(f"Expected a DICOM UID (digits and dots, at most 64), got {uid[:80]!r}")
        tmp = self.tmp / f"{uuid.uuid4().hex}.part"
        try:
            with open(tmp, "wb") as fh:
                write(fh)
                fh.flush()
                os.fsync(fh.fileno())
            with self._lock:
                folder = self.incoming / study_uid / series_uid
                if not folder.is_dir():
                    folder.mkdir(parents=True)
                    (folder / SENDER).write_text(json.dumps(sender))
                target = folder / f"{sop_uid}.dcm"
                existed = target.exists()
                os.replace(tmp, target)
                os.utime(folder)  # the series' clock restarts with every instance, new or repeated
            return existed
        finally:
            tmp.unlink(missing_ok=True)

    def pending(self) -> Iterator[tuple[str, str, float]]:
        """(study UID, series UID, seconds since its last instance) of every series still arriving."""
        now = time.time()
        for study in sorted(self.incoming.iterdir()):
            if not study.is_dir():
                continue
            for series in sorted(study.iterdir()):
                with contextlib.suppress(FileNotFoundError):
                    yield study.name, series.name, now - series.stat().st_mtime

    def claim_stable(self) -> list[ClaimedSeries]:
        """Take every series that has been quiet for ``stable_seconds`` out of ``incoming`` (and any claim left by
        an earlier run that stopped before making it a job)."""
        taken = [self._load(folder) for folder in sorted(self.claimed.iterdir()) if folder.is_dir()]
        for study_uid, series_uid, quiet in list(self.pending()):
            if quiet < self.stable_seconds:
                continue
            with self._lock:
                folder = self.incoming / study_uid / series_uid
                try:
                    if time.time() - folder.stat().st_mtime < self.stable_seconds:
                        continue  # an instance arrived meanwhile
                except FileNotFoundError:
                    continue
                (folder / ".uids").write_text(json.dumps([study_uid, series_uid]))
                target = self.claimed / uuid.uuid4().hex
                try:
                    os.replace(folder, target)
                except FileNotFoundError:  # another gateway on the same folder took it
                    continue
                with contextlib.suppress(OSError):
                    (self.incoming / study_uid).rmdir()  # empty now
            taken.append(self._load(target))
        return taken

    def _load(self, folder: Path) -> ClaimedSeries:
        try:
            study_uid, series_uid = json.loads((folder / ".uids").read_text())
        except (OSError, ValueError):
            study_uid = series_uid = ""
        try:
            sender = json.loads((folder / SENDER).read_text())
        except (OSError, ValueError):
            sender = {}
        return ClaimedSeries(folder, study_uid, series_uid, sender)

    def drop(self, series: ClaimedSeries) -> None:
        """Remove a claimed series that is not made into a job."""
        shutil.rmtree(series.folder, ignore_errors=True)

    def keep(self, series: ClaimedSeries) -> None:
        """Keep a claimed series that is not made into a job under ``kept/<series UID>`` (a newer copy replaces an
        older one), where a SEG drawn on it later finds it (``kept_series``) until ``expire_kept`` removes it."""
        if not is_uid(series.series_uid):
            self.drop(series)
            return
        target = self.kept / series.series_uid
        with self._lock:
            shutil.rmtree(target, ignore_errors=True)
            os.replace(series.folder, target)
            os.utime(target)  # kept from now

    def kept_series(self, series_uid: str) -> Path | None:
        """The kept folder of series ``series_uid``, or None."""
        folder = self.kept / series_uid
        return folder if is_uid(series_uid) and folder.is_dir() else None

    def expire_kept(self, max_age: float) -> int:
        """Remove the kept series older than ``max_age`` seconds; returns how many."""
        now, removed = time.time(), 0
        for folder in list(self.kept.iterdir()):
            with contextlib.suppress(FileNotFoundError):
                if now - folder.stat().st_mtime > max_age:
                    shutil.rmtree(folder, ignore_errors=True)
                    removed += 1
        return removed
