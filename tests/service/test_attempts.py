"""Each attempt at a job is recorded with its worker and host (``job_attempts``), on SQLite and PostgreSQL: a claim
opens one, the result closes it, a worker that went silent leaves it ``lost`` (taken over, or re-queued by the
reconciler), cancelling closes it as cancelled, deleting the job removes them; a database of the previous schema
version gets the table, with one attempt per claimed job from what its record knew."""

from __future__ import annotations

import contextlib
import datetime as dt

from sqlalchemy import text

from core import schema
from core.db import Database, owner_of, utcnow

OWNER = owner_of("key")


def later() -> dt.datetime:
    return utcnow() + dt.timedelta(seconds=1)


def test_attempts_name_their_worker_and_host_and_how_they_ended(db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:
        job = db.create(OWNER, {}, "scan.zip")
        first = db.claim(job.id, "hostA:11:aa", later(), name="bonemesh@hostA-11", host="hostA")
        assert first is not None and [(r.number, r.worker, r.host, r.outcome) for r in first.runs] == [
            (1, "bonemesh@hostA-11", "hostA", "running")
        ]
        second = db.claim(job.id, "hostB:22:bb", later(), name="bonemesh@hostB-22", host="hostB")  # A went silent
        assert second is not None
        assert [(r.worker, r.outcome) for r in second.runs] == [
            ("bonemesh@hostA-11", "lost"),
            ("bonemesh@hostB-22", "running"),
        ]
        assert second.runs[0].finished_at is not None and second.runs[1].finished_at is None
        assert not db.finish(job.id, "hostA:11:aa", "succeeded")  # the lost one cannot end it...
        assert db.finish(job.id, "hostB:22:bb", "succeeded", outputs=[])
        done = db.get(job.id)
        assert done is not None and [r.outcome for r in done.runs] == ["lost", "succeeded"]  # ...nor its row

        stale = db.create(OWNER, {}, "b.zip")
        assert db.claim(stale.id, "hostC:1:cc", utcnow())  # no name or host given: the token's
        assert db.requeue_stale(stale.id, later())  # the reconciler: its heartbeat stopped
        requeued = db.get(stale.id)
        assert requeued is not None and [(r.worker, r.host, r.outcome) for r in requeued.runs] == [
            ("hostC:1:cc", "hostC", "lost")
        ]
        assert db.claim(stale.id, "hostC:2:dd", utcnow()) and db.cancel(stale.id)
        cancelled = db.get(stale.id)
        assert cancelled is not None and [r.outcome for r in cancelled.runs] == ["lost", "cancelled"]

        rows, _ = db.list(OWNER, 10, 0)  # a listing carries them too
        assert {r.id: len(r.runs) for r in rows} == {job.id: 2, stale.id: 2}
        assert db.delete(job.id)
        with db.session() as s:
            left = s.execute(text("SELECT count(*) FROM job_attempts WHERE job_id = :j"), {"j": job.id}).scalar()
        assert left == 0


def test_the_upgrade_to_version_3_records_the_last_attempt_of_each_job(db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:  # made at this release's version, then taken back to 2
        ran = db.create(OWNER, {}, "a.zip")
        waiting = db.create(OWNER, {}, "b.zip")
        assert db.claim(ran.id, "oldhost:5:ee", utcnow())
        assert db.finish(ran.id, "oldhost:5:ee", "failed", error_code="bad_input", error_message="x")
        with db.engine.begin() as conn:
            conn.execute(text("DROP TABLE job_attempts"))
            conn.execute(text("DROP TABLE direct_uploads"))
            conn.execute(schema.VERSION_TABLE.update().values(version=2))
    with contextlib.closing(Database(db_url)) as db:
        assert schema.current_version(db.engine) == schema.VERSION
        upgraded, untouched = db.get(ran.id), db.get(waiting.id)
        assert upgraded is not None and untouched is not None and untouched.runs == []
        ((run,),) = [upgraded.runs]
        assert (run.number, run.worker, run.host, run.outcome) == (1, "oldhost:5:ee", "oldhost", "failed")
        assert run.finished_at == upgraded.finished_at
