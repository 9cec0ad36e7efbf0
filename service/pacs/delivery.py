"""Sending the model back: the job's ``model.dcm`` (Encapsulated STL, written by the worker), or a label job's
``labels.dcm.zip`` (one Encapsulated STL per label, all sent), by C-STORE to a DICOM node (one association) or
STOW-RS to a DICOMweb server (one request).

The ``pacs_jobs`` rows are the outbox: the dispatcher picks up succeeded jobs whose delivery is waiting or due for
a retry, claims each with one conditional update, sends, and records the outcome. A failure is retried with
exponential backoff (``delivery_backoff_seconds`` doubling up to ``delivery_max_backoff_seconds``, never sooner than a
DICOMweb server's ``Retry-After``) until
``delivery_max_attempts``; each failure is on the job (``delivery.state``, ``error``, ``next_attempt_at``), and a
dispatcher that dies mid-send leaves a claim that is taken again later. The instance's UIDs are fixed per job, so
a repeated send stores the same object again at the PACS, never a second one.
"""

from __future__ import annotations

import datetime as dt
import io
import zipfile
from collections.abc import Sequence
from typing import Any

from core.db import utcnow
from core.logsafe import escape_control, safe_logger
from core.pacs.config import DicomNode, DicomwebTarget, PacsSettings
from core.pacs.records import PacsJob, PacsRecords
from core.storage import Storage
from engine.export.files import LABELS_DCM, MODEL_DCM

log = safe_logger("bonemesh.pacs")
_C_STORE_OK = frozenset({0x0000, 0xB000, 0xB006, 0xB007})  # success, or stored with coercion / elements discarded


class DeliveryError(Exception):
    """A delivery attempt failed; the message says where and why (no patient data)."""


def send_c_store(node: DicomNode, calling_ae: str, datasets: Sequence[Any]) -> None:
    """C-STORE data sets (read with their file meta) to ``node`` in one association.

    Raises:
        DeliveryError: no association, or a failure status (naming how many were stored before it).
    """
    from pynetdicom import AE

    ae = AE(ae_title=calling_ae)
    for context in dict.fromkeys((ds.SOPClassUID, ds.file_meta.TransferSyntaxUID) for ds in datasets):
        ae.add_requested_context(*context)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = 30
    where = f"{node.ae_title}@{node.host}:{node.port}"
    assoc = ae.associate(node.host, node.port, ae_title=node.ae_title)
    if not assoc.is_established:
        how = "rejected" if assoc.is_rejected else "aborted" if assoc.is_aborted else "not established"
        raise DeliveryError(f"C-STORE to {where}: association {how}")
    try:
        for n, ds in enumerate(datasets):
            status = assoc.send_c_store(ds)
            code = int(status.Status) if status is not None and "Status" in status else None
            if code not in _C_STORE_OK:
                what = "no response" if code is None else f"status 0x{code:04X}"
                of = f" (object {n + 1} of {len(datasets)})" if len(datasets) > 1 else ""
                raise DeliveryError(f"C-STORE to {where}: {what}{of}")
    finally:
        assoc.release()


class Dispatcher:
    """Delivers due models (see the module docstring).

    Args:
        pacs: the settings (servers, calling AE title, backoff).
        records: the PACS records.
        storage: where the job outputs are.
    """

    def __init__(self, pacs: PacsSettings, records: PacsRecords, storage: Storage) -> None:
        self.pacs, self.records, self.storage = pacs, records, storage

    def run_once(self, now: dt.datetime | None = None) -> int:
        """Send every due model; returns how many were delivered."""
        now = now or utcnow()
        delivered = 0
        for job_id in self.records.due(now):
            rec = self.records.claim(job_id, now)
            if rec is not None:
                delivered += self._deliver(rec)
        return delivered

    def backoff(self, attempts: int, retry_after: float | None = None) -> float:
        """Seconds before the next try after ``attempts`` failed ones: the doubling backoff, and never sooner than
        a DICOMweb server's ``Retry-After`` asked (a STOW-RS 429 or 503; up to ``delivery_max_backoff_seconds``)."""
        cap = self.pacs.delivery_max_backoff_seconds
        base = self.pacs.delivery_backoff_seconds
        delay = float(min(base * 2 ** max(attempts - 1, 0), cap))
        return max(delay, min(float(retry_after), cap)) if retry_after else delay

    def _objects(self, job_id: str) -> list[Any] | None:
        """The job's DICOM objects: ``model.dcm``, or each member of a label job's ``labels.dcm.zip``; None when
        it has neither (read from a scratch copy off local disk)."""
        import pydicom

        with self.storage.local_output(job_id, MODEL_DCM) as path:
            if path is not None:
                return [pydicom.dcmread(path)]
        with self.storage.local_output(job_id, LABELS_DCM) as zipped:
            if zipped is None:
                return None
            with zipfile.ZipFile(zipped) as zf:
                return [pydicom.dcmread(io.BytesIO(zf.read(i))) for i in zf.infolist() if not i.is_dir()]

    def _deliver(self, rec: PacsJob) -> bool:
        job_id, dest = rec.job_id, rec.destination or {}
        missing = False
        try:
            objects = self._objects(job_id)
            if not objects:
                missing = True
                raise DeliveryError(
                    f"the job has no {MODEL_DCM} or {LABELS_DCM} (its source lacked a Frame of Reference UID?)"
                )
            self._send(dest, objects)
        except Exception as exc:
            message = escape_control(str(exc) or type(exc).__name__)
            final = missing or rec.delivery_attempts >= self.pacs.delivery_max_attempts
            delay = None if final else self.backoff(rec.delivery_attempts, getattr(exc, "retry_after", None))
            next_at = None if delay is None else utcnow() + dt.timedelta(seconds=delay)
            self.records.failed_attempt(job_id, message, next_at)
            log.warning(
                "job %s: delivery attempt %d failed: %s; %s",
                job_id,
                rec.delivery_attempts,
                message,
                "giving up" if delay is None else f"next try in {delay:g} s",
            )
            return False
        self.records.delivered(job_id)
        log.info("job %s: model delivered (%s) after %d attempt(s)", job_id, _describe(dest), rec.delivery_attempts)
        return True

    def _send(self, dest: dict[str, Any], objects: list[Any]) -> None:
        kind = dest.get("kind")
        if kind == "dicom":
            send_c_store(DicomNode.model_validate(dest), self.pacs.ae_title, objects)
        elif kind == "dicomweb":
            from core.pacs.dicomweb import store_datasets

            target = DicomwebTarget.model_validate(dest)
            server = self.pacs.dicomweb_servers.get(target.server)
            if server is None:
                raise DeliveryError(f"DICOMweb server {target.server!r} is not configured here")
            store_datasets(server, objects)
        else:
            raise DeliveryError(f"unknown destination kind {kind!r}")


def _describe(dest: dict[str, Any]) -> str:
    if dest.get("kind") == "dicom":
        return f"C-STORE to {dest.get('ae_title')}@{dest.get('host')}:{dest.get('port')}"
    return f"STOW-RS to {dest.get('server')}"
