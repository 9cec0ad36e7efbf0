"""The database's schema version, and the steps that bring an older database up to it.

Every API, worker and PACS process calls :func:`upgrade` when it opens the database (``core.db.Database``):

* a new database gets this release's tables and is stamped with :data:`VERSION`;
* a database made before versioning (release 0.1, tables made by ``create_all``) counts as version 0;
* a database at version N gets the steps after N, in order, then the stamp: one transaction under a lock (an
  advisory lock on PostgreSQL, ``BEGIN IMMEDIATE`` on SQLite), so processes starting together upgrade once and a
  failed step leaves the database as it was;
* a database stamped with a newer version than this release knows is refused (:class:`SchemaError`).

The stamp is the one row of the table ``bonemesh_schema``. A release that changes a table adds a step to
:data:`STEPS`: the steps are inspected before they act, so a step finds the change already made and skips it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from sqlalchemy import JSON, BigInteger, Column, DateTime, Integer, MetaData, String, Table, inspect, select, text
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import DBAPIError
from sqlalchemy.types import TypeEngine

log = logging.getLogger("bonemesh.schema")

VERSION_TABLE = Table("bonemesh_schema", MetaData(), Column("version", Integer, nullable=False))
PG_LOCK_KEY = 0x626F6E656D657368  # "bonemesh": the advisory lock held while the schema is checked and upgraded


class SchemaError(RuntimeError):
    """The database's schema cannot be brought to this release's (the message says why and what to do)."""


@dataclass(frozen=True)
class Step:
    """One upgrade: ``apply(conn)`` brings a database from version ``version - 1`` to ``version``."""

    version: int
    description: str
    apply: Callable[[Connection], None]


# --- the steps ---------------------------------------------------------------------------------------------------
# columns the job table gained after its first release (engine parameters, webhooks); all nullable
_V1_JOB_COLUMNS: dict[str, TypeEngine[Any]] = {
    "engine_params": JSON(),
    "callback_url": String(2048),
    "base_url": String(2048),
    "webhook_state": String(16),
    "webhook_next_at": DateTime(),
    "webhook_attempts": JSON(),
}
# sizes and counts: 64-bit (an upload over 2 GiB did not fit PostgreSQL's 32-bit INTEGER)
_V2_BIGINT_COLUMNS = (("jobs", "upload_bytes"), ("jobs", "attempts"), ("pacs_jobs", "delivery_attempts"))


def _v1_job_columns(conn: Connection) -> None:
    present = {c["name"] for c in inspect(conn).get_columns("jobs")}
    for name, kind in _V1_JOB_COLUMNS.items():
        if name not in present:
            conn.execute(text(f"ALTER TABLE jobs ADD COLUMN {name} {kind.compile(conn.dialect)}"))
    if not any(ix["name"] == "ix_jobs_webhook_state" for ix in inspect(conn).get_indexes("jobs")):
        conn.execute(text("CREATE INDEX ix_jobs_webhook_state ON jobs (webhook_state)"))


def _v2_bigint(conn: Connection) -> None:
    if conn.dialect.name == "sqlite":
        return  # SQLite's INTEGER is already 64-bit
    insp = inspect(conn)
    tables = set(insp.get_table_names())
    for table, column in _V2_BIGINT_COLUMNS:
        if table not in tables:
            continue  # made later with this release's types (pacs_jobs, by the first PACS process)
        kind = next(c["type"] for c in insp.get_columns(table) if c["name"] == column)
        if isinstance(kind, BigInteger):
            continue
        if conn.dialect.name != "postgresql":
            raise SchemaError(
                f"{table}.{column} is {kind}, not a 64-bit integer, and this release upgrades it only on SQLite "
                f"and PostgreSQL: change it to BIGINT by hand, then start again"
            )
        conn.execute(text(f"ALTER TABLE {table} ALTER COLUMN {column} TYPE BIGINT"))


def _v3_attempts(conn: Connection) -> None:
    """The tables ``job_attempts`` and ``direct_uploads`` are new (made by ``create_all`` before the steps run):
    each job that has been claimed gets one attempt row from what its record knew, its last worker and times (the
    host is the worker token's part before the first ``:``), unless it has rows already."""
    done = set(conn.execute(text("SELECT DISTINCT job_id FROM job_attempts")).scalars())
    rows = conn.execute(
        text(
            "SELECT id, worker, attempts, state, COALESCE(started_at, created_at), finished_at FROM jobs "
            "WHERE worker IS NOT NULL"
        )
    ).all()
    insert = text(
        "INSERT INTO job_attempts (job_id, number, claim, worker, host, started_at, finished_at, outcome) "
        "VALUES (:job_id, :number, :claim, :worker, :host, :started_at, :finished_at, :outcome)"
    )
    for job_id, worker, attempts, state, started_at, finished_at in rows:
        if job_id in done:
            continue
        ended = state in ("succeeded", "failed", "cancelled")
        conn.execute(
            insert,
            {
                "job_id": job_id,
                "number": max(int(attempts or 1), 1),
                "claim": worker,
                "worker": worker,
                "host": str(worker).split(":", 1)[0],
                "started_at": started_at,
                "finished_at": finished_at if ended else None,
                "outcome": state if ended else "running",
            },
        )


def _v4_idempotency(conn: Connection) -> None:
    """The table ``idempotency_keys`` is new (made by ``create_all`` before the steps run): nothing to move."""


STEPS = (
    Step(1, "job columns added after the first release (engine parameters, webhooks)", _v1_job_columns),
    Step(2, "64-bit sizes and counts (jobs.upload_bytes, jobs.attempts, pacs_jobs.delivery_attempts)", _v2_bigint),
    Step(3, "the worker and host of each attempt (job_attempts), and pending direct uploads", _v3_attempts),
    Step(4, "Idempotency-Key values of job and upload creation (idempotency_keys)", _v4_idempotency),
)
VERSION = STEPS[-1].version  # this release's schema


# --- applying them ------------------------------------------------------------------------------------------------
def current_version(engine: Engine) -> int | None:
    """The database's stamp; None when it has none (a new database, or one from before versioning)."""
    try:
        with engine.connect() as conn:
            return conn.execute(select(VERSION_TABLE.c.version)).scalar()
    except DBAPIError:  # no such table
        return None


def upgrade(engine: Engine, metadata: MetaData) -> int:
    """Bring the database to :data:`VERSION`, making ``metadata``'s tables where missing; returns the version it
    had before (:data:`VERSION` for a new or current database, 0 for one from before versioning).

    Raises:
        SchemaError: the database is newer than this release, or a step failed.
    """
    if current_version(engine) == VERSION:
        return VERSION  # the common case: no lock taken
    with _locked(engine) as conn:
        names = set(inspect(conn).get_table_names())
        if VERSION_TABLE.name in names:
            found = conn.execute(select(VERSION_TABLE.c.version)).scalar()
        else:
            found = 0 if names & set(metadata.tables) else None
        if found is not None and found > VERSION:
            raise SchemaError(
                f"the database's schema is version {found}, newer than this release's ({VERSION}): "
                f"run the release that upgraded it (or a newer one)"
            )
        metadata.create_all(conn)  # tables it lacks, as this release makes them
        VERSION_TABLE.create(conn, checkfirst=True)
        start = VERSION if found is None else found
        for step in STEPS[start:]:
            log.warning("upgrading the database schema to version %d: %s", step.version, step.description)
            try:
                step.apply(conn)
            except SchemaError:
                raise
            except Exception as exc:
                raise SchemaError(
                    f"upgrading the database schema from version {start} to {VERSION} failed at step "
                    f"{step.version} ({step.description}): {exc}"
                ) from exc
        conn.execute(VERSION_TABLE.delete())
        conn.execute(VERSION_TABLE.insert().values(version=VERSION))
        return VERSION if found is None else found


@contextmanager
def _locked(engine: Engine) -> Iterator[Connection]:
    """One transaction that no other process upgrading the same database runs beside (committed on success)."""
    with engine.connect() as conn:
        if conn.dialect.name == "sqlite":
            conn.exec_driver_sql("BEGIN IMMEDIATE")  # the write lock now (waits out the busy timeout)
        elif conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": PG_LOCK_KEY})
        yield conn
        conn.commit()
