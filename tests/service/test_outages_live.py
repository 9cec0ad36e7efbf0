"""Outages of a real deployment's parts (issue 43), with the real processes: the job database (PostgreSQL) going
away and coming back: while it is down, reads and uploads answer 503 with ``Retry-After`` and a problem type of their
own (``urn:bonemesh:problem:database_unavailable``), never a generic 500, and leave nothing half-made; once it is
back, the same requests succeed without restarting the API. And the file store (SeaweedFS) stopping under a job:
re-queued and finished once it is back, or failed with ``storage_unavailable`` when it stays down."""

from __future__ import annotations

import time

import httpx

from tests.service.conftest import HEADSQ, StackFactory
from tests.service.postgres import PostgresServer
from tests.service.procs import submit, wait_for_job
from tests.service.seaweed import SeaweedServer

OUTAGE = "urn:bonemesh:problem:database_unavailable"


def _outage(resp: httpx.Response) -> dict:
    assert resp.status_code == 503, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    assert int(resp.headers["Retry-After"]) > 0
    body = resp.json()
    assert body["type"] == OUTAGE and body["code"] == "database_unavailable", body
    assert "job database" in body["detail"] and "try again" in body["detail"]
    return body


def test_the_api_answers_503_while_postgresql_is_down(make_stack: StackFactory, postgres_server: PostgresServer):
    url = postgres_server.create_database()
    _, stack = make_stack(workers=0, extra_env={"BONEMESH_DATABASE_URL": url})
    with stack.client() as client:
        first = submit(client, HEADSQ.path, HEADSQ.params)
        assert first.status_code == 202, first.text
        job_id = first.json()["id"]
        postgres_server.stop()
        try:
            _outage(client.get("/v1/jobs"))
            _outage(client.get(f"/v1/jobs/{job_id}"))
            _outage(submit(client, HEADSQ.path, HEADSQ.params))
            uploads = stack.data_dir / "jobs"
            kept = [p.parent.name for p in uploads.rglob("*") if p.is_file()]
            assert set(kept) <= {job_id}, kept  # the refused upload left nothing behind
        finally:
            postgres_server.start()
        deadline = time.monotonic() + 60
        while True:  # the API's pool reconnects by itself
            resp = client.get(f"/v1/jobs/{job_id}")
            if resp.status_code == 200 or time.monotonic() > deadline:
                break
            _outage(resp)
            time.sleep(0.5)
        assert resp.status_code == 200 and resp.json()["id"] == job_id, resp.text
        again = submit(client, HEADSQ.path, HEADSQ.params)
        assert again.status_code == 202, again.text
        assert client.get("/v1/jobs").json()["total"] == 2


def test_a_job_waits_out_a_store_outage_and_fails_with_its_code_when_it_lasts(
    make_stack: StackFactory, seaweed_server: SeaweedServer
) -> None:
    """SeaweedFS stopped after the upload: the worker gives the job back to the queue (an ``outage`` attempt, not
    counted as its worker's failure) and it succeeds once the store is back; a store that stays down fails the job
    with ``storage_unavailable`` after the bounded re-queues, never ``internal_error``."""
    bucket = seaweed_server.make_bucket()
    env = {**seaweed_server.env(bucket, "outage"), "BONEMESH_OUTAGE_SECONDS": "8", "BONEMESH_OUTAGE_REQUEUES": "2"}
    _, stack = make_stack(workers=0, extra_env=env)
    with stack.client() as client:
        waited = submit(client, HEADSQ.path, HEADSQ.params)
        assert waited.status_code == 202, waited.text
        seaweed_server.stop()
        try:
            stack.start_worker()

            def given_back(job: dict) -> bool:
                return any(run["outcome"] == "outage" for run in job["runs"])

            job = wait_for_job(client, waited.json()["id"], stack=stack, timeout=180, until=given_back)
            assert job["state"] in ("queued", "running") and job["error"] is None, job
        finally:
            seaweed_server.restart()
        job = wait_for_job(client, waited.json()["id"], stack=stack, timeout=300)
        assert job["state"] == "succeeded", job
        assert [run["outcome"] for run in job["runs"]][-1] == "succeeded" and given_back(job)

        lasting = submit(client, HEADSQ.path, HEADSQ.params)
        assert lasting.status_code == 202, lasting.text
        seaweed_server.stop()
        try:
            job = wait_for_job(client, lasting.json()["id"], stack=stack, timeout=300)
        finally:
            seaweed_server.restart()
        assert job["state"] == "failed" and job["error"]["code"] == "storage_unavailable", job
        assert "file store was unreachable" in job["error"]["message"]
        assert [run["outcome"] for run in job["runs"]].count("outage") == 2
