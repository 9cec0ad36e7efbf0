"""``bonemesh pacs``: the storage SCP, the sweep that turns stable series into jobs, and the delivery dispatcher,
in one process.

    bonemesh pacs [--host H] [--port P] [--ae-title AE] [--deliver-only]

A stable series is routed (:mod:`core.pacs.routing`); a taken one is moved whole into the job's upload folder
(``jobs/<id>/upload/``) and recorded in the same job table, with the same queue message, as an uploaded scan: the
worker cannot tell them apart. A segmentation (SEG) takes the CT series it references along (``reference/`` in its
upload, copied from the job that series became, or from the CT series kept when no rule took it, for
``keep_unrouted_seconds``): it waits while that series is still arriving, and for ``reference_wait_seconds`` for one
not received yet; after that its job fails, saying the series is missing.
Settings: :mod:`core.pacs.config` (``BONEMESH_PACS_*``) and
:mod:`core.settings` (``BONEMESH_*``: database, data folder, broker).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import signal
import threading
import time
from pathlib import Path
from typing import Any

from core.db import Database, Job, owner_of
from core.logsafe import safe_logger
from core.pacs.config import PacsSettings, get_pacs_settings
from core.pacs.records import PacsRecords, is_uid
from core.pacs.routing import REFERENCE_FOLDER, SeriesSummary, choose_rule, not_a_volume
from core.queue import Queue
from core.settings import Settings, get_settings
from core.storage import storage_from_settings
from service.pacs.delivery import Dispatcher
from service.pacs.inbox import SENDER, ClaimedSeries, Inbox
from service.pacs.scp import StorageSCP

log = safe_logger("bonemesh.pacs")


def summarize(series: ClaimedSeries) -> SeriesSummary:
    """What routing needs of a claimed series: the first image's header and the image count."""
    import pydicom

    files = series.files()
    ds = pydicom.dcmread(files[0], stop_before_pixels=True, force=True)
    frames = int(ds.get("NumberOfFrames", 1) or 1)
    return SeriesSummary(
        study_uid=series.study_uid,
        series_uid=series.series_uid,
        modality=str(ds.get("Modality", "")),
        images=len(files) * frames,
        description=str(ds.get("SeriesDescription", "")),
        body_part=str(ds.get("BodyPartExamined", "")),
        image_type=tuple(str(v) for v in (ds.get("ImageType") or ())),
    )


def _copy_series(src: Path, target: Path) -> None:
    """Copy a series' DICOM files into ``target`` whole or not at all (a temporary name, renamed)."""
    part = target.with_name(f".{target.name}.part")
    shutil.rmtree(part, ignore_errors=True)
    shutil.copytree(src, part, ignore=shutil.ignore_patterns(REFERENCE_FOLDER, ".*"))
    os.replace(part, target)


def _is_seg(series: ClaimedSeries) -> bool:
    """Whether a claimed series is a segmentation (by its first file's SOP class)."""
    from engine.labels.uploads import is_seg_file

    files = series.files()
    return bool(files) and is_seg_file(files[0])


class Gateway:
    """The pieces of ``bonemesh pacs``, built from the settings.

    Args:
        settings: the service's settings (database, data folder, broker, API keys).
        pacs: the PACS settings.
    """

    def __init__(self, settings: Settings, pacs: PacsSettings) -> None:
        self.settings, self.pacs = settings, pacs
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.db = Database(settings.db_url)
        self.records = PacsRecords(self.db)
        self.storage = storage_from_settings(settings)
        self.queue = Queue(settings.redis_url, settings.queue)
        self.inbox = Inbox(settings.data_dir / "pacs", pacs.stable_seconds)
        self.scp = StorageSCP(pacs, self.inbox)
        self.dispatcher = Dispatcher(pacs, self.records, self.storage)
        key = pacs.owner_key.get_secret_value() if pacs.owner_key else settings.api_keys[0]
        self.owner = owner_of(key)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    # -- series -> jobs ---------------------------------------------------------------------------------------
    def sweep_once(self) -> list[str]:
        """Turn every stable series into a job or drop it; returns the new job ids."""
        made = []
        self.inbox.expire_kept(self.pacs.keep_unrouted_seconds)
        claimed = self.inbox.claim_stable()
        claimed.sort(key=_is_seg)  # a CT before the SEGs, which may reference it
        for series in claimed:
            try:
                job_id = self.make_job(series)
            except Exception:
                log.exception(
                    "series %s of study %s: could not be made a job; kept to retry", series.series_uid, series.study_uid
                )
                continue
            if job_id:
                made.append(job_id)
        return made

    def make_job(self, series: ClaimedSeries) -> str | None:
        """Route one claimed series; a taken one becomes a queued job (its id is returned)."""
        files = series.files()
        if not files:
            self.inbox.drop(series)
            return None
        try:
            summary = summarize(series)
        except Exception as exc:  # nothing to route on: drop it rather than retry it forever
            log.warning(
                "series %s of study %s dropped: its first image is unreadable (%s)",
                series.series_uid,
                series.study_uid,
                type(exc).__name__,
            )
            self.inbox.drop(series)
            return None
        rule, why = choose_rule(summary, self.pacs.routes)
        if rule is None:
            is_ct = summary.modality.upper() == "CT" and not not_a_volume(summary)
            keep = is_ct and self.pacs.keep_unrouted_seconds > 0
            log.info(
                "series %s of study %s ignored: %s%s",
                series.series_uid,
                series.study_uid,
                why,
                f"; kept {self.pacs.keep_unrouted_seconds:g} s for a SEG drawn on it" if keep else "",
            )
            (self.inbox.keep if keep else self.inbox.drop)(series)
            return None
        if summary.modality.upper() == "SEG" and not self._attach_reference(series):
            return None  # kept claimed: the CT it references may still come
        job_id = Database.new_id()
        for extra in (SENDER, ".uids"):
            (series.folder / extra).unlink(missing_ok=True)
        size = sum(p.stat().st_size for p in files)
        sender = series.sender.get("ae_title", "?")
        job = Job(
            id=job_id,
            owner=self.owner,
            state="queued",
            params=rule.job_params().record(),
            upload_name=f"DICOM C-STORE from {sender} ({summary.images} images)",
            upload_bytes=size,
        )
        source = {
            "kind": "dimse",
            "calling_ae": sender,
            "study_uid": series.study_uid,
            "series_uid": series.series_uid,
            "images": summary.images,  # frames of multi-frame images counted
        }
        dest = self.pacs.destination.model_dump() if self.pacs.destination else None
        # the series becomes the job's upload; back to the claim if the record fails (the next sweep tries again)
        with self.storage.put_upload_folder(job_id, series.folder):
            self.records.create_job(job, source, dest, rule=rule.name)
        log.info(
            "series %s of study %s: %d images from %s -> job %s (%s)",
            series.series_uid,
            series.study_uid,
            len(files),
            sender,
            job_id,
            why,
        )
        try:
            self.queue.enqueue(job_id)
            self.db.mark_enqueued(job_id)
        except Exception as exc:  # the API's reconciler sends it later
            log.warning("job %s: could not enqueue (%s); it stays queued and is re-sent later", job_id, exc)
        return job_id

    def _attach_reference(self, series: ClaimedSeries) -> bool:
        """Copy the CT series a SEG references into its folder (``reference/``) from the job that series became.
        True when attached, or when waiting is over (the job then fails, naming the missing series); False to wait:
        the series is still arriving, or has not come yet and ``reference_wait_seconds`` have not passed."""
        target = series.folder / REFERENCE_FOLDER
        if target.is_dir():
            return True  # an earlier sweep attached it
        import pydicom

        from engine.labels.dicom_seg import referenced_series

        wanted = referenced_series(pydicom.dcmread(series.files()[0], stop_before_pixels=True, force=True))
        if not wanted or not is_uid(wanted):
            return True  # nothing to wait for: the worker says so
        if any(self.inbox.incoming.glob(f"*/{wanted}")):
            return False
        ct_job = self.records.latest_of_series(wanted)
        if ct_job is not None and self.storage.has_upload(ct_job):
            with self.storage.local_upload(ct_job) as src:
                _copy_series(src, target)
            log.info("SEG series %s: its referenced series %s taken from job %s", series.series_uid, wanted, ct_job)
            return True
        kept = self.inbox.kept_series(wanted)  # a CT no rule took
        if kept is not None:
            _copy_series(kept, target)
            log.info("SEG series %s: its referenced series %s taken from the kept series", series.series_uid, wanted)
            return True
        waited = time.time() - series.folder.stat().st_mtime
        if waited < self.pacs.reference_wait_seconds:
            return False
        log.warning(
            "SEG series %s: its referenced series %s was not received within %g s; its job fails saying so",
            series.series_uid,
            wanted,
            self.pacs.reference_wait_seconds,
        )
        return True

    # -- the process ------------------------------------------------------------------------------------------
    def _loop(self, name: str, step: Any) -> None:
        while not self._stop.wait(self.pacs.poll_seconds):
            try:
                step()
            except Exception:
                log.exception("%s failed; trying again", name)

    def start(self, receive: bool = True) -> None:
        """Start the SCP and the sweep (unless ``receive`` is false) and the delivery loop (background threads)."""
        loops: list[tuple[str, Any]] = [("delivery", self.dispatcher.run_once)]
        if receive:
            self.scp.start()
            loops.append(("sweep", self.sweep_once))
        for name, step in loops:
            thread = threading.Thread(target=self._loop, args=(name, step), name=f"pacs-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        self._stop.set()
        self.scp.stop()
        for thread in self._threads:
            thread.join(timeout=10)


def main(argv: list[str] | None = None) -> int:
    """``bonemesh pacs``: run until SIGTERM or Ctrl-C."""
    parser = argparse.ArgumentParser(
        prog="bonemesh pacs",
        description="DICOM storage SCP: receive CT series from a PACS, run them as jobs, send the models back.",
    )
    parser.add_argument("--host", help="listen address (default BONEMESH_PACS_HOST)")
    parser.add_argument("--port", type=int, help="listen port (default BONEMESH_PACS_PORT)")
    parser.add_argument("--ae-title", help="this node's AE title (default BONEMESH_PACS_AE_TITLE)")
    parser.add_argument(
        "--deliver-only", action="store_true", help="no storage SCP: only send models back (DICOMweb-only sites)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    pacs = get_pacs_settings()
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port), ("ae_title", args.ae_title)) if v}
    if overrides:
        pacs = pacs.model_copy(update=overrides)
    if not pacs.allow and not args.deliver_only:
        log.error(
            "BONEMESH_PACS_ALLOW is empty: no sender would be accepted. Set it to the calling AE titles of "
            "your PACS, e.g. BONEMESH_PACS_ALLOW=ORTHANC,PACS1@10.0.0.5"
        )
        return 2
    gateway = Gateway(get_settings(), pacs)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    gateway.start(receive=not args.deliver_only)
    callers = ", ".join(e.ae_title + (f"@{e.address}" if e.address else "") for e in pacs.allow)
    log.info(
        "%s; destination of C-STORE jobs: %s",
        "delivery only, no storage SCP"
        if args.deliver_only
        else f"allowed callers: {callers}; series stable after {pacs.stable_seconds:g} s",
        pacs.destination.model_dump() if pacs.destination else "none",
    )
    stop.wait()
    gateway.stop()
    return 0
