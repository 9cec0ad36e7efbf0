"""The job database on both backends (SQLite, and a real PostgreSQL: ``tests.service.postgres``): 64-bit sizes and
counts, the job operations the units don't reach, the schema upgrade of a database made before versioning (also by
processes starting together), and one job through the real API and worker on PostgreSQL."""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import threading
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import BigInteger, Column, Integer, MetaData, Table, create_engine, inspect, update

from core import schema
from core.db import Database, Job, owner_of, utcnow
from core.pacs.records import PacsJob, PacsRecords
from tests.service.checks import assert_succeeded
from tests.service.conftest import HEADSQ, StackFactory
from tests.service.postgres import PostgresServer
from tests.service.procs import submit, wait_for_job

OVER_4_GIB = 5 * 2**30  # past 32 bits signed (PostgreSQL's INTEGER) and unsigned
BIGINT_COLUMNS = (("jobs", "upload_bytes"), ("jobs", "attempts"), ("pacs_jobs", "delivery_attempts"))
# the job table's columns added after its first release (step 1 of core.schema adds them)
LATER_JOB_COLUMNS = (
    "engine_params",
    "callback_url",
    "base_url",
    "webhook_state",
    "webhook_next_at",
    "webhook_attempts",
)


def column_types(db: Database) -> dict[tuple[str, str], Any]:
    insp = inspect(db.engine)
    return {(t, c): next(col["type"] for col in insp.get_columns(t) if col["name"] == c) for t, c in BIGINT_COLUMNS}


def test_sizes_and_counts_are_64_bit(db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:
        records = PacsRecords(db)
        for (table, column), kind in column_types(db).items():
            assert isinstance(kind, BigInteger), f"{table}.{column} is {kind}"
        job = db.create(owner_of("key"), {"iso": 1150}, "large.zip", upload_bytes=OVER_4_GIB)
        again = db.get(job.id, owner_of("key"))
        assert again is not None and again.upload_bytes == OVER_4_GIB and again.params == {"iso": 1150}
        pacs = Job(id=Database.new_id(), owner="o", state="succeeded", params={}, upload_name="x", upload_bytes=3 << 30)
        records.create_job(pacs, {"kind": "dimse", "ae_title": "CT1"}, {"kind": "dicom", "ae_title": "PACS"})
        with db.session() as s:
            s.execute(update(PacsJob).values(delivery_attempts=2**40))
        rec = records.get(pacs.id)
        assert rec is not None and rec.delivery_attempts == 2**40 and rec.source["ae_title"] == "CT1"
        assert schema.current_version(db.engine) == schema.VERSION


def test_reconciling_and_webhook_operations(db_url: str) -> None:
    """What the reconciler and the webhook sender do, conditional updates included (their rowcounts decide)."""
    with contextlib.closing(Database(db_url)) as db:
        owner = owner_of("key")
        queued = db.create(owner, {}, "a.zip", 10)
        running = db.create(owner, {}, "b.zip", 20, callback_url="https://example.org/hook", base_url="http://x")
        later = utcnow() + dt.timedelta(seconds=5)
        assert db.claim(running.id, "w1", stale_before=utcnow()) is not None
        assert db.lost_jobs(queued_before=later, stale_before=utcnow() - dt.timedelta(hours=1)) == ([queued.id], [])
        db.mark_enqueued(queued.id)
        enqueued = db.get(queued.id)
        assert enqueued is not None and enqueued.enqueued_at is not None
        assert db.lost_jobs(queued_before=enqueued.enqueued_at, stale_before=later) == ([], [running.id])
        assert not db.requeue_stale(running.id, stale_before=utcnow() - dt.timedelta(hours=1))  # heartbeat fresh
        assert db.requeue_stale(running.id, stale_before=later)
        assert db.get(running.id).state == "queued"  # type: ignore[union-attr]
        assert db.claim(running.id, "w2", stale_before=utcnow()) is not None
        assert db.due_webhooks(utcnow()) == []  # not finished yet
        assert db.finish(running.id, "w2", "failed", error_code="input", error_message="bad slices")
        (due,) = db.due_webhooks(utcnow())
        assert due.id == running.id and due.webhook_state == "pending"
        assert db.lease_webhook(due, until=later)
        assert not db.lease_webhook(due, until=later)  # another API process read the same row: it loses
        db.record_webhook(running.id, {"status": 500}, "pending", next_at=utcnow() - dt.timedelta(seconds=1))
        (due,) = db.due_webhooks(utcnow())
        assert due.webhook_attempts == [{"status": 500}] and db.lease_webhook(due, until=later)
        db.record_webhook(running.id, {"status": 204}, "delivered", next_at=None)
        assert db.due_webhooks(later) == []
        assert db.delete(queued.id) and not db.delete(queued.id) and db.get(queued.id) is None
        rows, total = db.list(owner, limit=10, offset=0)
        assert total == 1 and rows[0].webhook_state == "delivered" and rows[0].error_code == "input"


def first_release_tables() -> MetaData:
    """The tables as releases before versioning made them: sizes and counts INTEGER (32-bit on PostgreSQL), the job
    table without the columns added after the first release, no stamp."""
    md = MetaData()
    for table, left_out in (
        (Job.metadata.tables["jobs"], LATER_JOB_COLUMNS),
        (PacsJob.metadata.tables["pacs_jobs"], ()),
    ):
        columns = [
            Column(
                c.name,
                Integer() if isinstance(c.type, BigInteger) else c.type,
                primary_key=c.primary_key,
                nullable=c.nullable,
                index=c.index,
            )
            for c in table.columns
            if c.name not in left_out
        ]
        Table(table.name, md, *columns)
    return md


def make_first_release_database(url: str) -> str:
    """An old database at ``url`` holding one job with its PACS record; returns the job's id."""
    md = first_release_tables()
    engine = create_engine(url)
    job_id = Database.new_id()
    try:
        md.create_all(engine)
        with engine.begin() as conn:
            conn.execute(
                md.tables["jobs"]
                .insert()
                .values(
                    id=job_id,
                    owner=owner_of("key"),
                    state="succeeded",
                    progress=100.0,
                    params={"iso": 1150},
                    upload_name="old.zip",
                    upload_bytes=2**31 - 1,  # the most a 32-bit column held
                    attempts=1,
                    created_at=utcnow(),
                )
            )
            conn.execute(
                md.tables["pacs_jobs"]
                .insert()
                .values(
                    job_id=job_id,
                    source={"kind": "dimse"},
                    result_series_uid="2.25.1",
                    result_sop_uid="2.25.2",
                    delivery_state="delivered",
                    delivery_attempts=2,
                )
            )
    finally:
        engine.dispose()
    return job_id


def upgrades(caplog: pytest.LogCaptureFixture, version: int) -> int:
    return sum(f"schema to version {version}:" in r.getMessage() for r in caplog.records)


def test_a_database_from_before_versioning_is_upgraded(db_url: str, caplog: pytest.LogCaptureFixture) -> None:
    job_id = make_first_release_database(db_url)
    engine = create_engine(db_url)
    assert schema.current_version(engine) is None
    engine.dispose()
    with caplog.at_level(logging.WARNING, "bonemesh.schema"), contextlib.closing(Database(db_url)) as db:
        assert [upgrades(caplog, v) for v in (1, 2)] == [1, 1]
        assert schema.current_version(db.engine) == schema.VERSION
        present = {c["name"] for c in inspect(db.engine).get_columns("jobs")}
        assert present >= set(LATER_JOB_COLUMNS)
        if db.engine.dialect.name == "postgresql":  # SQLite's INTEGER is 64-bit already: left as it is
            assert all(isinstance(kind, BigInteger) for kind in column_types(db).values()), column_types(db)
        job = db.get(job_id, owner_of("key"))
        assert job is not None and job.upload_bytes == 2**31 - 1 and job.params == {"iso": 1150}
        assert job.callback_url is None and job.webhook_attempts is None
        with db.session() as s:
            s.execute(update(Job).where(Job.id == job_id).values(upload_bytes=OVER_4_GIB))
        assert db.get(job_id).upload_bytes == OVER_4_GIB  # type: ignore[union-attr]
        rec = PacsRecords(db).get(job_id)
        assert rec is not None and rec.delivery_state == "delivered" and rec.delivery_attempts == 2
        new = db.create(owner_of("key"), {}, "new.zip", OVER_4_GIB, callback_url="https://example.org/hook")
        assert db.get(new.id).webhook_state == "pending"  # type: ignore[union-attr]
    caplog.clear()
    with caplog.at_level(logging.WARNING, "bonemesh.schema"), contextlib.closing(Database(db_url)):
        assert upgrades(caplog, 2) == 0  # current: nothing to do


def test_processes_starting_together_upgrade_once(db_url: str, caplog: pytest.LogCaptureFixture) -> None:
    """API processes and workers open an old database together: one upgrades it, the others wait and find it done."""
    make_first_release_database(db_url)
    together = threading.Barrier(4)
    opened: list[Database] = []
    errors: list[BaseException] = []

    def open_db() -> None:
        together.wait()
        try:
            opened.append(Database(db_url))
        except BaseException as exc:
            errors.append(exc)

    with caplog.at_level(logging.WARNING, "bonemesh.schema"):
        threads = [threading.Thread(target=open_db) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    try:
        assert errors == [] and len(opened) == 4
        assert upgrades(caplog, 2) == 1
        assert schema.current_version(opened[0].engine) == schema.VERSION
    finally:
        for db in opened:
            db.close()


def test_a_database_newer_than_the_release_is_refused(db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db, db.engine.begin() as conn:
        conn.execute(schema.VERSION_TABLE.update().values(version=schema.VERSION + 1))
    with pytest.raises(schema.SchemaError, match=f"version {schema.VERSION + 1}, newer than this release"):
        Database(db_url).close()


def test_a_job_through_the_api_and_a_worker_on_postgresql(
    make_stack: StackFactory, postgres_server: PostgresServer
) -> None:
    url = postgres_server.create_database()
    _, stack = make_stack(extra_env={"BONEMESH_DATABASE_URL": url})
    with stack.client() as client:
        resp = submit(client, HEADSQ.path, HEADSQ.params)
        assert resp.status_code == 202, resp.text
        job = wait_for_job(client, resp.json()["id"], stack=stack, timeout=300)
        assert_succeeded(job, stack.base_url)
        assert job["upload_bytes"] == Path(HEADSQ.path).stat().st_size and job["attempts"] == 1
        listed = client.get("/v1/jobs").json()
        assert [j["id"] for j in listed["items"]] == [job["id"]] and listed["total"] == 1
        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert client.get(f"/v1/jobs/{job['id']}").status_code == 404
    with contextlib.closing(Database(url)) as db:  # the API and the worker used PostgreSQL, not a file
        assert db.list(owner_of(stack.env["BONEMESH_API_KEYS"].split(",")[0]), 10, 0) == ([], 0)
        assert schema.current_version(db.engine) == schema.VERSION
    assert not list(stack.data_dir.glob("*.db"))
