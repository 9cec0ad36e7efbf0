"""The ``pacs_jobs`` table: for a job that came from a PACS, where it came from (no credentials, no patient data:
the kind, the sender's AE title or the server's name, Study and Series Instance UIDs) and where its model goes,
with the delivery's state. It sits beside the job table in the same database (created when missing), so the job
table itself is unchanged.

Delivery states: ``waiting`` (for the job), ``sending`` (claimed by a dispatcher), ``retrying`` (failed, next try at
``next_attempt_at``), ``delivered``, ``failed`` (gave up after the last attempt; the error says why), ``none`` (no
destination). A job that failed or was cancelled shows ``skipped``.
"""

from __future__ import annotations

import datetime as dt
import re
import uuid
from typing import Any

from sqlalchemy import JSON, BigInteger, DateTime, String, Text, select, update
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from core.db import Database, Job, create_tables, utcnow
from engine.export.files import LABELS_DCM

SENDING_STALE = dt.timedelta(minutes=5)  # a claim older than this was lost with its dispatcher
UID_ROOT = "2.25."  # UUID-derived UIDs (PS3.5 B.2): no registered root needed


class _Base(DeclarativeBase):
    pass


class PacsJob(_Base):
    """The PACS side of one job."""

    __tablename__ = "pacs_jobs"

    job_id: Mapped[str] = mapped_column(String(32), primary_key=True)
    source: Mapped[dict[str, Any]] = mapped_column(JSON)
    rule: Mapped[str | None] = mapped_column(String(64), default=None)
    destination: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    result_series_uid: Mapped[str] = mapped_column(String(64))
    result_sop_uid: Mapped[str] = mapped_column(String(64))
    delivery_state: Mapped[str] = mapped_column(String(16), index=True, default="waiting")
    delivery_attempts: Mapped[int] = mapped_column(BigInteger, default=0)
    delivery_error: Mapped[str | None] = mapped_column(Text, default=None)
    next_attempt_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    claimed_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    delivered_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)


def result_uids(job_id: str) -> tuple[str, str]:
    """The model's Series and SOP Instance UIDs, derived from the job id: a repeated delivery stores the same
    instance again (idempotent at the PACS), never a second copy."""
    n = int(job_id, 16)
    return f"{UID_ROOT}{n}", f"{UID_ROOT}{(n + 1) % (1 << 128)}"


UID = re.compile(r"^[0-9]+(\.[0-9]+)*$")


def is_uid(value: str) -> bool:
    """Whether ``value`` is a well-formed DICOM UID (digits and dots, at most 64 characters)."""
    return 0 < len(value) <= 64 and bool(UID.match(value))


def label_sop_uid(job_id: str, value: int) -> str:
    """The SOP Instance UID of a label job's model of label ``value`` (fixed per job and label, as ``result_uids``)."""
    return f"{UID_ROOT}{uuid.uuid5(uuid.UUID(hex=job_id), f'label-{value}').int}"


class PacsRecords:
    """PACS records in the job database."""

    def __init__(self, db: Database) -> None:
        self.db = db
        create_tables(_Base.metadata, db.engine)

    def create_job(
        self,
        job: Job,
        source: dict[str, Any],
        destination: dict[str, Any] | None,
        rule: str | None = None,
    ) -> None:
        """Record a job and its PACS side in one transaction."""
        series_uid, sop_uid = result_uids(job.id)
        pacs = PacsJob(
            job_id=job.id,
            source=source,
            rule=rule,
            destination=destination,
            result_series_uid=series_uid,
            result_sop_uid=sop_uid,
            delivery_state="waiting" if destination else "none",
        )
        with self.db.session() as s:
            s.add(job)
            s.add(pacs)

    def get(self, job_id: str) -> PacsJob | None:
        with self.db.session() as s:
            return s.get(PacsJob, job_id)

    def latest_of_series(self, series_uid: str) -> str | None:
        """The newest job made from series ``series_uid`` (received or fetched), or None."""
        with self.db.session() as s:
            return s.scalars(
                select(PacsJob.job_id)
                .join(Job, Job.id == PacsJob.job_id)
                .where(PacsJob.source["series_uid"].as_string() == series_uid)
                .order_by(Job.created_at.desc())
                .limit(1)
            ).first()

    def due(self, now: dt.datetime, limit: int = 20) -> list[str]:
        """Jobs whose model is ready to send now: succeeded, waiting or retrying and due, or a lost claim."""
        with self.db.session() as s:
            rows = s.scalars(
                select(PacsJob.job_id)
                .join(Job, Job.id == PacsJob.job_id)
                .where(
                    Job.state == "succeeded",
                    (PacsJob.delivery_state == "waiting")
                    | ((PacsJob.delivery_state == "retrying") & (PacsJob.next_attempt_at <= now))
                    | ((PacsJob.delivery_state == "sending") & (PacsJob.claimed_at < now - SENDING_STALE)),
                )
                .order_by(PacsJob.next_attempt_at.asc().nulls_first())  # waiting ones first, as on SQLite
                .limit(limit)
            ).all()
            return list(rows)

    def claim(self, job_id: str, now: dt.datetime) -> PacsJob | None:
        """Take a due delivery (one conditional update; None when another dispatcher has it)."""
        with self.db.session() as s:
            res = s.execute(
                update(PacsJob)
                .where(
                    PacsJob.job_id == job_id,
                    (PacsJob.delivery_state.in_(("waiting", "retrying")))
                    | ((PacsJob.delivery_state == "sending") & (PacsJob.claimed_at < now - SENDING_STALE)),
                )
                .values(delivery_state="sending", claimed_at=now, delivery_attempts=PacsJob.delivery_attempts + 1)
            )
            if res.rowcount != 1:
                return None
            return s.get(PacsJob, job_id)

    def delivered(self, job_id: str) -> None:
        with self.db.session() as s:
            s.execute(
                update(PacsJob)
                .where(PacsJob.job_id == job_id)
                .values(delivery_state="delivered", delivered_at=utcnow(), delivery_error=None, next_attempt_at=None)
            )

    def failed_attempt(self, job_id: str, error: str, next_at: dt.datetime | None) -> None:
        """Record a failed attempt: retry at ``next_at``, or give up (``failed``) when it is None."""
        with self.db.session() as s:
            s.execute(
                update(PacsJob)
                .where(PacsJob.job_id == job_id)
                .values(
                    delivery_state="retrying" if next_at else "failed",
                    delivery_error=error[:2000],
                    next_attempt_at=next_at,
                )
            )

    def redeliver(self, job_id: str) -> bool:
        """Send a finished job's model again (``POST /v1/jobs/{id}/deliver``): a delivered, given-up or retrying
        delivery goes back to ``waiting`` with a fresh count of attempts; one waiting or being sent is left as it
        is (the request is idempotent). The model keeps its UIDs, so the PACS stores the same instance again.
        False when the job has no destination."""
        with self.db.session() as s:
            res = s.execute(
                update(PacsJob)
                .where(PacsJob.job_id == job_id, PacsJob.delivery_state.in_(("delivered", "failed", "retrying")))
                .values(
                    delivery_state="waiting",
                    delivery_attempts=0,
                    delivery_error=None,
                    next_attempt_at=None,
                    claimed_at=None,
                )
            )
            if res.rowcount == 1:
                return True
            rec = s.get(PacsJob, job_id)
            return rec is not None and rec.delivery_state != "none"

    def view(self, job: Job) -> dict[str, Any]:
        """The job resource's ``source`` and ``delivery`` entries ({} for an uploaded job)."""
        rec = self.get(job.id)
        if rec is None:
            return {}
        state = rec.delivery_state
        if state == "waiting" and job.state in ("failed", "cancelled"):
            state = "skipped"
        delivery = {
            "state": state,
            "destination": rec.destination,
            "attempts": rec.delivery_attempts,
            "error": rec.delivery_error,
            "next_attempt_at": _utc(rec.next_attempt_at),
            "delivered_at": _utc(rec.delivered_at),
            "series_instance_uid": rec.result_series_uid,
            # a label job sends one object per label (labels.dcm.zip), all in the series: no one SOP instance
            "sop_instance_uid": None if _has_output(job, LABELS_DCM) else rec.result_sop_uid,
        }
        return {"source": {**rec.source, "rule": rec.rule}, "delivery": delivery}


def _has_output(job: Job, name: str) -> bool:
    return any(o.get("name") == name for o in job.outputs or [])


def _utc(value: dt.datetime | None) -> dt.datetime | None:
    return None if value is None else value.replace(tzinfo=dt.UTC)
