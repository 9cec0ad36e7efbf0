"""Job records (SQLAlchemy; SQLite by default, or PostgreSQL; both tested): the truth about every job. The broker
only carries wake-up calls; a job whose message is lost is re-enqueued from here.

A worker *claims* a job with one conditional UPDATE (queued, or running with a stale heartbeat), so a duplicate
message never runs a job twice at once, and writes progress, heartbeat and the result only while its claim holds.

Each claim also writes a row of ``job_attempts``: which worker (its name and host) ran the attempt, when, and how
it ended (``running`` until then; ``lost`` when its worker stopped and the job was taken over or re-queued). Direct
uploads not yet completed (``direct_uploads``, ``service.direct``) wait in a table of their own, and so do the
``Idempotency-Key`` values of job and upload creation (``idempotency_keys``, ``service.idempotency``).

Opening the database brings its schema to this release's (``core.schema``: versioned upgrade steps). Sizes and
counts are 64-bit (``BigInteger``): uploads reach 4 GiB, past PostgreSQL's 32-bit ``INTEGER``.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    DateTime,
    Float,
    Integer,
    String,
    Text,
    create_engine,
    delete,
    event,
    func,
    select,
    update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship, sessionmaker

from core import schema

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
ACTIVE = ("queued", "running")
TERMINAL = ("succeeded", "failed", "cancelled")
OPEN = "running"  # the outcome of an attempt not ended yet
LOST = "lost"  # the outcome of an attempt whose worker stopped (killed, or silent past the staleness limit)
OUTAGE = "outage"  # the outcome of an attempt given back because the database or the store was down
ORIENTING = "orienting"  # the stage of a succeeded job whose outputs are being re-oriented (worker.tasks.orient_job)


def utcnow() -> dt.datetime:
    """Now, in UTC, without tzinfo (as stored)."""
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


def owner_of(api_key: str) -> str:
    """The stored owner of a key's jobs: a hash, never the key itself."""
    return hashlib.sha256(api_key.encode()).hexdigest()[:32]


class Base(DeclarativeBase):
    pass


class Job(Base):
    """One reconstruction job."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(64), index=True)
    state: Mapped[str] = mapped_column(String(16), index=True, default="queued")
    stage: Mapped[str | None] = mapped_column(String(32), default=None)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    upload_name: Mapped[str] = mapped_column(String(255), default="")
    upload_bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    error_code: Mapped[str | None] = mapped_column(String(32), default=None)
    error_message: Mapped[str | None] = mapped_column(Text, default=None)
    outputs: Mapped[list[dict[str, Any]] | None] = mapped_column(JSON, default=None)
    attempts: Mapped[int] = mapped_column(BigInteger, default=0)
    worker: Mapped[str | None] = mapped_column(String(128), default=None)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow, index=True)
    enqueued_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    started_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    # the engine's own parameters (``{"recon": ReconParams.to_dict(), "spacing_zyx_mm": ...}``), made once by the API
    engine_params: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    # webhook: where to POST the job on its terminal state, and how the deliveries went (service.webhooks)
    callback_url: Mapped[str | None] = mapped_column(String(2048), default=None)
    base_url: Mapped[str | None] = mapped_column(String(2048), default=None)
    webhook_state: Mapped[str | None] = mapped_column(String(16), default=None, index=True)
    webhook_next_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    webhook_attempts: Mapped[list[dict[str, Any]] | None] = mapped_column(JSON, default=None)
    # each attempt's worker and host, oldest first (loaded with the job: one more query for a whole list)
    runs: Mapped[list[Attempt]] = relationship(
        "Attempt",
        primaryjoin="Job.id == foreign(Attempt.job_id)",
        order_by="Attempt.number",
        lazy="selectin",
        viewonly=True,
    )


class Attempt(Base):
    """One attempt at a job: the worker that claimed it (``claim``: the job's ``worker`` token while it held it),
    the worker's name and host, and how it ended."""

    __tablename__ = "job_attempts"

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    number: Mapped[int] = mapped_column(BigInteger)
    claim: Mapped[str] = mapped_column(String(128))
    worker: Mapped[str] = mapped_column(String(255))
    host: Mapped[str] = mapped_column(String(255))
    started_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    outcome: Mapped[str] = mapped_column(String(16), default=OPEN)


class PendingUpload(Base):
    """A direct upload begun (``POST /v1/uploads``) and not yet completed or aborted: the job it becomes (its id is
    the job's), the store's multipart upload, and what the client declared (validated once, at the start)."""

    __tablename__ = "direct_uploads"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(64), index=True)
    store_upload_id: Mapped[str] = mapped_column(String(1024))
    state: Mapped[str] = mapped_column(String(16), default="open")  # open, then completing
    upload_name: Mapped[str] = mapped_column(String(255))
    upload_bytes: Mapped[int] = mapped_column(BigInteger)
    part_bytes: Mapped[int] = mapped_column(BigInteger)
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    engine_params: Mapped[dict[str, Any]] = mapped_column(JSON)
    callback_url: Mapped[str | None] = mapped_column(String(2048), default=None)
    base_url: Mapped[str | None] = mapped_column(String(2048), default=None)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    expires_at: Mapped[dt.datetime] = mapped_column(DateTime, index=True)


class IdempotencyKey(Base):
    """An ``Idempotency-Key`` a client sent with a request that creates something (``scope``: ``POST /v1/jobs``,
    ``POST /v1/uploads``), per key owner: ``pending`` while its first request runs (``token`` names that request,
    ``touched_at`` its last sign of life), then ``done`` with the request's fingerprint, what it made and the status it
    answered. Removed at ``expires_at`` (``BONEMESH_IDEMPOTENCY_TTL_SECONDS``) and with the job it names."""

    __tablename__ = "idempotency_keys"

    owner: Mapped[str] = mapped_column(String(64), primary_key=True)
    scope: Mapped[str] = mapped_column(String(32), primary_key=True)
    key: Mapped[str] = mapped_column(String(255), primary_key=True)
    token: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), default="pending")  # pending, then done
    fingerprint: Mapped[str | None] = mapped_column(String(64), default=None)
    resource_id: Mapped[str | None] = mapped_column(String(32), default=None, index=True)
    status_code: Mapped[int | None] = mapped_column(Integer, default=None)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    touched_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    expires_at: Mapped[dt.datetime] = mapped_column(DateTime, index=True)


def _end_attempts(s: Session, job_id: str, outcome: str, claim: str | None = None) -> None:
    """Close the job's open attempts (only ``claim``'s when given) with ``outcome``."""
    cond = [Attempt.job_id == job_id, Attempt.finished_at.is_(None)]
    if claim is not None:
        cond.append(Attempt.claim == claim)
    s.execute(update(Attempt).where(*cond).values(outcome=outcome, finished_at=utcnow()))


class Database:
    """The engine, sessions and the job operations used by the API and the worker."""

    def __init__(self, url: str) -> None:
        kwargs: dict[str, Any] = {}
        if url.startswith("sqlite"):
            kwargs["connect_args"] = {"timeout": 30, "check_same_thread": False}
        self.engine: Engine = create_engine(url, pool_pre_ping=True, **kwargs)
        if url.startswith("sqlite"):
            event.listen(self.engine, "connect", _sqlite_pragmas)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        try:
            _schema_step(lambda: schema.upgrade(self.engine, Base.metadata))
        except BaseException:
            self.engine.dispose()
            raise

    def close(self) -> None:
        """Close the pool's connections (a process that opens the database again gets new ones)."""
        self.engine.dispose()

    @contextmanager
    def session(self) -> Iterator[Session]:
        with self._sessions() as s, s.begin():
            yield s

    def ping(self) -> None:
        with self.session() as s:
            s.execute(select(1))

    # --- API side -----------------------------------------------------------------------------------------------
    def create(
        self,
        owner: str,
        params: dict[str, Any],
        upload_name: str,
        upload_bytes: int = 0,
        job_id: str | None = None,
        *,
        engine_params: dict[str, Any] | None = None,
        callback_url: str | None = None,
        base_url: str | None = None,
    ) -> Job:
        job = Job(
            id=job_id or uuid.uuid4().hex,
            owner=owner,
            state="queued",
            params=params,
            upload_name=upload_name,
            upload_bytes=upload_bytes,
            engine_params=engine_params,
            callback_url=callback_url,
            base_url=base_url,
            webhook_state="pending" if callback_url else None,
            webhook_attempts=[] if callback_url else None,
        )
        with self.session() as s:
            s.add(job)
        return job

    @staticmethod
    def new_id() -> str:
        return uuid.uuid4().hex

    def get(self, job_id: str, owner: str | None = None) -> Job | None:
        with self.session() as s:
            job = s.get(Job, job_id)
            if job is None or (owner is not None and job.owner != owner):
                return None
            return job

    def list(self, owner: str, limit: int, offset: int) -> tuple[list[Job], int]:
        with self.session() as s:
            total = s.scalar(select(func.count()).select_from(Job).where(Job.owner == owner)) or 0
            query = select(Job).where(Job.owner == owner).order_by(Job.created_at.desc(), Job.id)
            rows = s.scalars(query.limit(limit).offset(offset)).all()
            return list(rows), int(total)

    def mark_enqueued(self, job_id: str) -> None:
        with self.session() as s:
            s.execute(update(Job).where(Job.id == job_id).values(enqueued_at=utcnow()))

    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job (its worker notices at its next heartbeat); the record stays, as cancelled.
        True if it was active; a finished job is left as it is."""
        with self.session() as s:
            res = s.execute(
                update(Job)
                .where(Job.id == job_id, Job.state.in_(ACTIVE))
                .values(state="cancelled", finished_at=utcnow(), outputs=None)
            )
            if res.rowcount == 1:
                _end_attempts(s, job_id, "cancelled")
            return res.rowcount == 1

    def delete(self, job_id: str) -> bool:
        """Remove a job's record (a running job's worker notices at its next heartbeat). True if it existed."""
        with self.session() as s:
            s.execute(delete(Attempt).where(Attempt.job_id == job_id))
            s.execute(delete(IdempotencyKey).where(IdempotencyKey.resource_id == job_id))
            return s.execute(delete(Job).where(Job.id == job_id)).rowcount == 1

    def lost_jobs(self, queued_before: dt.datetime, stale_before: dt.datetime) -> tuple[list[str], list[str]]:
        """Queued jobs enqueued before ``queued_before`` (their message may be gone) and running jobs whose
        heartbeat is older than ``stale_before`` (their worker is gone)."""
        with self.session() as s:
            queued = s.scalars(
                select(Job.id).where(
                    Job.state == "queued",
                    Job.created_at < queued_before,
                    (Job.enqueued_at.is_(None)) | (Job.enqueued_at < queued_before),
                )
            ).all()
            stale = s.scalars(select(Job.id).where(Job.state == "running", Job.heartbeat_at < stale_before)).all()
            return list(queued), list(stale)

    def requeue_stale(self, job_id: str, stale_before: dt.datetime) -> bool:
        """Put a running job whose heartbeat stopped back in the queue."""
        with self.session() as s:
            res = s.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == "running", Job.heartbeat_at < stale_before)
                .values(state="queued", stage="queued", worker=None)
            )
            if res.rowcount == 1:
                _end_attempts(s, job_id, LOST)
            return res.rowcount == 1

    def release(self, job_id: str, worker: str, stage: str) -> bool:
        """Put a job this ``worker`` holds back in the queue because something it depends on is down (an outage, not
        the worker's doing: its attempt ends as ``outage``, not counted against ``max_attempts``); ``stage`` says what
        it waits for. False when the worker no longer holds it."""
        with self.session() as s:
            res = s.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == "running", Job.worker == worker)
                .values(state="queued", stage=stage, worker=None)
            )
            if res.rowcount == 1:
                _end_attempts(s, job_id, OUTAGE, worker)
            return res.rowcount == 1

    def outages(self, job_id: str) -> int:
        """How often the job was given back for an outage (``release``)."""
        with self.session() as s:
            return int(s.scalar(select(func.count()).where(Attempt.job_id == job_id, Attempt.outcome == OUTAGE)) or 0)

    def start_orient(self, job_id: str, stale_before: dt.datetime) -> bool:
        """Mark a succeeded job as being re-oriented (``stage="orienting"``; it stays succeeded, its files
        downloadable). False when it has not succeeded, or a re-orientation younger than ``stale_before`` runs."""
        with self.session() as s:
            res = s.execute(
                update(Job)
                .where(
                    Job.id == job_id,
                    Job.state == "succeeded",
                    (Job.stage.is_(None)) | (Job.stage != ORIENTING) | (Job.heartbeat_at < stale_before),
                )
                .values(stage=ORIENTING, heartbeat_at=utcnow(), error_code=None, error_message=None)
            )
            return res.rowcount == 1

    # --- worker side --------------------------------------------------------------------------------------------
    def claim(
        self, job_id: str, worker: str, stale_before: dt.datetime, *, name: str | None = None, host: str | None = None
    ) -> Job | None:
        """Take a job for ``worker`` (a token unique to this run): it must be queued, or running with a heartbeat
        older than ``stale_before``. Counts an attempt and records it with the worker's ``name`` and ``host``
        (default: the token, and its part before the first ``:``); an attempt left open by a silent worker ends as
        ``lost``. None when another worker holds it or it is finished or cancelled."""
        now = utcnow()
        with self.session() as s:
            res = s.execute(
                update(Job)
                .where(
                    Job.id == job_id,
                    (Job.state == "queued") | ((Job.state == "running") & (Job.heartbeat_at < stale_before)),
                )
                .values(
                    state="running",
                    worker=worker,
                    attempts=Job.attempts + 1,
                    started_at=now,
                    heartbeat_at=now,
                    stage="starting",
                    progress=0.0,
                    error_code=None,
                    error_message=None,
                )
            )
            if res.rowcount != 1:
                return None
            _end_attempts(s, job_id, LOST)
            number = s.scalar(select(Job.attempts).where(Job.id == job_id)) or 1
            s.add(
                Attempt(
                    job_id=job_id,
                    number=number,
                    claim=worker,
                    worker=name or worker,
                    host=host or worker.split(":", 1)[0],
                    started_at=now,
                )
            )
            s.flush()
            return s.get(Job, job_id)

    def beat(self, job_id: str, worker: str, stage: str | None = None, progress: float | None = None) -> bool:
        """Heartbeat (and progress) of the holder; False when the claim is gone (cancelled or taken over)."""
        values: dict[str, Any] = {"heartbeat_at": utcnow()}
        if stage is not None:
            values["stage"] = stage
        if progress is not None:
            values["progress"] = progress
        with self.session() as s:
            res = s.execute(
                update(Job).where(Job.id == job_id, Job.worker == worker, Job.state == "running").values(**values)
            )
            return res.rowcount == 1

    def finish_orient(self, job_id: str, **values: Any) -> bool:
        """End a re-orientation (``stage="done"``, with the new outputs and params, or an error): only while the
        job is still succeeded and re-orienting."""
        with self.session() as s:
            res = s.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == "succeeded", Job.stage == ORIENTING)
                .values(stage="done", **values)
            )
            return res.rowcount == 1

    def finish(self, job_id: str, worker: str | None, state: str, **values: Any) -> bool:
        """Final state, written only while ``worker`` holds the job (any holder when ``worker`` is None)."""
        cond = [Job.id == job_id, Job.state.in_(ACTIVE)]
        if worker is not None:
            cond += [Job.worker == worker, Job.state == "running"]
        with self.session() as s:
            res = s.execute(update(Job).where(*cond).values(state=state, finished_at=utcnow(), **values))
            if res.rowcount == 1:
                _end_attempts(s, job_id, state, worker)
            return res.rowcount == 1

    # --- idempotency keys (API side: service.idempotency) --------------------------------------------------------
    def reserve_key(
        self, owner: str, scope: str, key: str, token: str, expires_at: dt.datetime, stale_before: dt.datetime
    ) -> IdempotencyKey | None:
        """Take ``key`` for the request ``token``: None when taken (a new key, or one past ``expires_at``, or one
        whose first request stopped touching it before ``stale_before``), else the row that holds it."""
        where = (IdempotencyKey.owner == owner, IdempotencyKey.scope == scope, IdempotencyKey.key == key)
        now = utcnow()
        try:
            with self.session() as s:
                s.execute(
                    delete(IdempotencyKey).where(
                        *where,
                        (IdempotencyKey.expires_at <= now)
                        | ((IdempotencyKey.state == "pending") & (IdempotencyKey.touched_at < stale_before)),
                    )
                )
                row = IdempotencyKey(owner=owner, scope=scope, key=key, token=token, state="pending")
                row.created_at = row.touched_at = now
                row.expires_at = expires_at
                s.add(row)
            return None
        except IntegrityError:  # held: by a request still running, or done
            with self.session() as s:
                held = s.scalars(select(IdempotencyKey).where(*where)).first()
            if held is None:  # gone between the two (expired and swept): try once more
                return self.reserve_key(owner, scope, key, token, expires_at, stale_before)
            return held

    def touch_key(self, owner: str, scope: str, key: str, token: str) -> bool:
        """The request ``token`` still runs; False when it no longer holds the key (taken over as stale)."""
        with self.session() as s:
            res = s.execute(
                update(IdempotencyKey)
                .where(*_held_by(owner, scope, key, token), IdempotencyKey.state == "pending")
                .values(touched_at=utcnow())
            )
            return res.rowcount == 1

    def finish_key(
        self, owner: str, scope: str, key: str, token: str, fingerprint: str, resource_id: str, status_code: int
    ) -> bool:
        """Record what the request ``token`` made with the key (only while it holds it)."""
        with self.session() as s:
            res = s.execute(
                update(IdempotencyKey)
                .where(*_held_by(owner, scope, key, token))
                .values(state="done", fingerprint=fingerprint, resource_id=resource_id, status_code=status_code)
            )
            return res.rowcount == 1

    def release_key(self, owner: str, scope: str, key: str, token: str) -> None:
        """Give the key up (its request failed: the same key may be sent again)."""
        with self.session() as s:
            s.execute(
                delete(IdempotencyKey).where(*_held_by(owner, scope, key, token), IdempotencyKey.state == "pending")
            )

    def sweep_keys(self, now: dt.datetime) -> int:
        """Remove the keys past their expiry; how many."""
        with self.session() as s:
            return int(s.execute(delete(IdempotencyKey).where(IdempotencyKey.expires_at <= now)).rowcount or 0)

    # --- webhooks (API side) -------------------------------------------------------------------------------------
    def due_webhooks(self, now: dt.datetime, limit: int = 20) -> list[Job]:
        """Finished jobs whose webhook is pending and due."""
        with self.session() as s:
            query = select(Job).where(
                Job.webhook_state == "pending",
                Job.state.in_(TERMINAL),
                (Job.webhook_next_at.is_(None)) | (Job.webhook_next_at <= now),
            )
            return list(s.scalars(query.order_by(Job.finished_at).limit(limit)).all())

    def lease_webhook(self, job: Job, until: dt.datetime) -> bool:
        """Take the next delivery of ``job``'s webhook (another API process that read the same row loses)."""
        with self.session() as s:
            cond = [Job.id == job.id, Job.webhook_state == "pending"]
            cond.append(
                Job.webhook_next_at.is_(None)
                if job.webhook_next_at is None
                else Job.webhook_next_at == job.webhook_next_at
            )
            return s.execute(update(Job).where(*cond).values(webhook_next_at=until)).rowcount == 1

    def record_webhook(self, job_id: str, attempt: dict[str, Any], state: str, next_at: dt.datetime | None) -> None:
        """Append a delivery attempt; ``state`` pending (retry at ``next_at``), delivered or failed."""
        with self.session() as s:
            job = s.get(Job, job_id)
            if job is None:
                return
            job.webhook_attempts = [*(job.webhook_attempts or []), attempt]
            job.webhook_state = state
            job.webhook_next_at = next_at


def create_tables(metadata: Any, engine: Engine) -> None:
    """``metadata.create_all``, safe when several processes start at once (API processes, workers): one that loses
    the race to create a table sees it on the next try."""
    _schema_step(lambda: metadata.create_all(engine))


def _schema_step(step: Any, tries: int = 5) -> None:
    """Run a schema step, again while it fails because another process did the same thing just before."""
    from sqlalchemy.exc import OperationalError, ProgrammingError

    for attempt in range(tries):
        try:
            step()
            return
        except (OperationalError, ProgrammingError) as exc:
            if attempt == tries - 1 or not any(s in str(exc).lower() for s in ("already exists", "duplicate")):
                raise


WAL_TRIES = 100  # x 0.05 s: how long a new connection waits for another process to finish switching to WAL


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    """WAL and a 30 s busy timeout for every connection. Processes starting together on a new database (API
    processes, workers) all switch it to WAL; SQLite answers one of two such switches "database is locked" at once,
    without waiting (its deadlock avoidance), so the switch is tried again: by then the other made it, and it is a
    no-op."""
    import sqlite3

    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA busy_timeout=30000")
    for attempt in range(WAL_TRIES):
        try:
            cur.execute("PRAGMA journal_mode=WAL")
            break
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or attempt == WAL_TRIES - 1:
                raise
            time.sleep(0.05)
    cur.close()


def _held_by(owner: str, scope: str, key: str, token: str) -> tuple[Any, ...]:
    """The conditions of an Idempotency-Key row held by the request ``token``."""
    return (
        IdempotencyKey.owner == owner,
        IdempotencyKey.scope == scope,
        IdempotencyKey.key == key,
        IdempotencyKey.token == token,
    )
