"""``Idempotency-Key`` on ``POST /v1/jobs`` and ``POST /v1/uploads`` (``service.idempotency``): the same key with the
same request gives the same job, with another request 422; the key is held in the database (SQLite and
PostgreSQL), per API key, for a bounded time. Tested on the app, on both databases, and on a real ``bonemesh serve``
with a multipart upload cut off half way and sent again, and one whose answer was lost."""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import socket
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from core.db import Database, IdempotencyKey, utcnow
from core.settings import Settings
from service import idempotency
from tests.service.conftest import HEADSQ, StackFactory
from tests.service.procs import wait_until

KEY_A = {"X-API-Key": "key-a"}
KEY_B = {"X-API-Key": "key-b"}


def _app(tmp_path: Path, **settings: Any) -> TestClient:
    from service.app import create_app

    base = {
        "data_dir": tmp_path,
        "api_keys": ["key-a", "key-b"],
        "secret_key": "s" * 32,
        "redis_url": "redis://127.0.0.1:1/0",
        "reconcile_seconds": 3600,
    }
    return TestClient(create_app(Settings(**{**base, **settings})))


def _upload(client: TestClient | httpx.Client, key: str | None, params: dict[str, Any], **headers: str) -> Any:
    files = {"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")}
    sent = {**headers, **({"Idempotency-Key": key} if key is not None else {})}
    return client.post("/v1/jobs", headers=sent, files=files, data={"params": json.dumps(params)})


def test_an_upload_is_hashed_only_under_a_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The fingerprint (the SHA-256 of the upload's bytes) is made only where a key will compare it: an upload
    without one is not hashed, one with a key is, over every byte of its file."""
    made: list[idempotency.UploadPrint] = []

    class Counted(idempotency.UploadPrint):
        def __init__(self) -> None:
            super().__init__()
            made.append(self)

    monkeypatch.setattr(idempotency, "UploadPrint", Counted)
    with _app(tmp_path) as client:
        assert _upload(client, None, HEADSQ.params, **KEY_A).status_code == 202
        assert made == []
        assert _upload(client, str(uuid.uuid4()), HEADSQ.params, **KEY_A).status_code == 202
        assert [m.file.hexdigest() for m in made] == [hashlib.sha256(HEADSQ.path.read_bytes()).hexdigest()]


def test_the_same_key_and_request_give_the_same_job(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        key = str(uuid.uuid4())
        first = _upload(client, key, HEADSQ.params, **KEY_A)
        assert first.status_code == 202, first.text
        assert idempotency.REPLAYED.lower() not in first.headers
        # sent again (httpx picks a new multipart boundary each time; the params' keys in another order)
        again = _upload(client, key, dict(reversed(list(HEADSQ.params.items()))), **KEY_A)
        assert again.status_code == 202, again.text
        assert again.json()["id"] == first.json()["id"]
        assert again.headers["location"] == first.headers["location"] == f"/v1/jobs/{first.json()['id']}"
        assert again.headers[idempotency.REPLAYED] == "true"
        assert client.get("/v1/jobs", headers=KEY_A).json()["total"] == 1
        # another body with the same key: 422, its own problem type, nothing made
        other = _upload(client, key, {**HEADSQ.params, "iso": 900}, **KEY_A)
        assert other.status_code == 422, other.text
        body = other.json()
        assert body["type"] == "urn:bonemesh:problem:idempotency_key_reused"
        assert body["code"] == "idempotency_key_reused"
        assert other.headers["content-type"] == "application/problem+json"
        files = {"file": ("other.zip", HEADSQ.path.read_bytes(), "application/zip")}
        renamed = client.post("/v1/jobs", headers={**KEY_A, "Idempotency-Key": key}, files=files,
                              data={"params": json.dumps(HEADSQ.params)})  # fmt: skip
        assert renamed.status_code == 422, renamed.text
        assert client.get("/v1/jobs", headers=KEY_A).json()["total"] == 1
        # the key is per API key: key-b's same key makes key-b's own job
        theirs = _upload(client, key, HEADSQ.params, **KEY_B)
        assert theirs.status_code == 202 and theirs.json()["id"] != first.json()["id"]
        # no key: a new job each time
        assert _upload(client, None, HEADSQ.params, **KEY_A).json()["id"] != first.json()["id"]
        assert client.get("/v1/jobs", headers=KEY_A).json()["total"] == 2


def test_a_failed_request_gives_its_key_up_and_a_deleted_job_forgets_it(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        key = "retry-" + uuid.uuid4().hex
        bad = _upload(client, key, {**HEADSQ.params, "iso": "not a number"}, **KEY_A)
        assert bad.status_code == 422 and bad.json()["code"] == "invalid_request", bad.text
        good = _upload(client, key, HEADSQ.params, **KEY_A)  # the mistake fixed, the same key
        assert good.status_code == 202 and idempotency.REPLAYED.lower() not in good.headers, good.text
        assert client.delete(f"/v1/jobs/{good.json()['id']}", headers=KEY_A).status_code == 204
        fresh = _upload(client, key, HEADSQ.params, **KEY_A)
        assert fresh.status_code == 202 and fresh.json()["id"] != good.json()["id"]


def test_a_key_held_by_a_running_request_answers_409_until_it_goes_stale(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        db: Database = client.app.state.services.db  # type: ignore[attr-defined]
        owner = db_owner("key-a")
        key = "busy-" + uuid.uuid4().hex
        later = utcnow() + dt.timedelta(hours=1)
        assert db.reserve_key(owner, idempotency.JOBS, key, "other-request", later, utcnow()) is None
        busy = _upload(client, key, HEADSQ.params, **KEY_A)
        assert busy.status_code == 409, busy.text
        assert busy.json()["type"] == "urn:bonemesh:problem:idempotency_key_in_use"
        assert int(busy.headers["retry-after"]) > 0
        assert client.get("/v1/jobs", headers=KEY_A).json()["total"] == 0
        stale = utcnow() - dt.timedelta(seconds=idempotency.STALE_SECONDS + 1)
        with db.session() as s:  # its request stopped (killed) a while ago
            s.execute(update(IdempotencyKey).where(IdempotencyKey.key == key).values(touched_at=stale))
        taken = _upload(client, key, HEADSQ.params, **KEY_A)
        assert taken.status_code == 202, taken.text
        assert not db.touch_key(owner, idempotency.JOBS, key, "other-request")  # the old holder lost it


def test_keys_expire_after_the_ttl(tmp_path: Path) -> None:
    with _app(tmp_path, idempotency_ttl_seconds=60) as client:
        db: Database = client.app.state.services.db  # type: ignore[attr-defined]
        key = "ttl-" + uuid.uuid4().hex
        first = _upload(client, key, HEADSQ.params, **KEY_A).json()["id"]
        with db.session() as s:
            row = s.get(IdempotencyKey, (db_owner("key-a"), idempotency.JOBS, key))
            assert row is not None and row.state == "done" and row.resource_id == first
            assert abs((row.expires_at - row.created_at).total_seconds() - 60) < 1
        assert db.sweep_keys(utcnow()) == 0
        assert db.sweep_keys(utcnow() + dt.timedelta(seconds=61)) == 1  # the background sweep's call
        second = _upload(client, key, HEADSQ.params, **KEY_A)
        assert second.status_code == 202 and second.json()["id"] != first


def test_the_key_header_is_checked_and_documented(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        for bad in ("x" * 256, " padded "):
            resp = _upload(client, bad, HEADSQ.params, **KEY_A)
            assert resp.status_code == 422 and "Idempotency-Key" in resp.text, resp.text
        spec = client.get("/openapi.json").json()
        for path in ("/v1/jobs", "/v1/uploads"):
            names = [p["name"] for p in spec["paths"][path]["post"].get("parameters", [])]
            assert "Idempotency-Key" in names, path


def test_dicomweb_json_jobs_take_the_key_too(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(
        "BONEMESH_PACS_DICOMWEB_SERVERS", json.dumps({"pacs": {"url": "https://pacs.example.org/dicomweb"}})
    )
    from core.pacs.config import get_pacs_settings

    get_pacs_settings.cache_clear()
    try:
        with _app(tmp_path) as client:
            body = {"source": {"dicomweb": {"server": "pacs", "study_uid": "1.2.3", "series_uid": "1.2.3.4"}}}
            headers = {**KEY_A, "Idempotency-Key": "json-" + uuid.uuid4().hex}
            first = client.post("/v1/jobs", headers=headers, json=body)
            if first.status_code == 422 and "source" in first.text:
                pytest.skip(f"the DICOMweb body of this release differs: {first.text}")
            assert first.status_code == 202, first.text
            again = client.post("/v1/jobs", headers=headers, json=body)
            assert again.status_code == 202 and again.json()["id"] == first.json()["id"]
            other = client.post("/v1/jobs", headers=headers, json={**body, "deliver": False})
            assert other.status_code == 422 and other.json()["code"] == "idempotency_key_reused", other.text
    finally:
        get_pacs_settings.cache_clear()


def db_owner(api_key: str) -> str:
    from core.db import owner_of

    return owner_of(api_key)


def test_the_api_on_both_databases(tmp_path: Path, db_url: str) -> None:
    with _app(tmp_path, database_url=db_url) as client:
        key = "db-" + uuid.uuid4().hex
        first = _upload(client, key, HEADSQ.params, **KEY_A)
        again = _upload(client, key, HEADSQ.params, **KEY_A)
        assert first.status_code == again.status_code == 202 and again.json()["id"] == first.json()["id"]
        assert _upload(client, key, {**HEADSQ.params, "iso": 900}, **KEY_A).json()["code"] == "idempotency_key_reused"
        assert _upload(client, key, HEADSQ.params, **KEY_B).json()["id"] != first.json()["id"]
        assert client.get("/v1/jobs", headers=KEY_A).json()["total"] == 1
        db: Database = client.app.state.services.db  # type: ignore[attr-defined]
    db.close()


# -- the database: SQLite and PostgreSQL ---------------------------------------------------------------------------
def test_keys_in_the_database(db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:
        later, now = utcnow() + dt.timedelta(hours=1), utcnow()
        assert db.reserve_key("o", "s", "k", "t1", later, now - dt.timedelta(minutes=1)) is None
        held = db.reserve_key("o", "s", "k", "t2", later, now - dt.timedelta(minutes=1))
        assert held is not None and held.token == "t1" and held.state == "pending"
        assert db.reserve_key("other-owner", "s", "k", "t3", later, now) is None  # per owner
        assert db.reserve_key("o", "other-scope", "k", "t4", later, now) is None  # per operation
        assert db.touch_key("o", "s", "k", "t1") and not db.touch_key("o", "s", "k", "t2")
        assert db.finish_key("o", "s", "k", "t1", "f" * 64, "job1", 202)
        done = db.reserve_key("o", "s", "k", "t5", later, utcnow() + dt.timedelta(minutes=5))  # done: never stale
        assert done is not None and (done.state, done.resource_id, done.status_code) == ("done", "job1", 202)
        db.release_key("o", "s", "k", "t1")  # a done key is not given up
        assert db.reserve_key("o", "s", "k", "t6", later, now) is not None
        db.release_key("other-owner", "s", "k", "t3")
        assert db.reserve_key("other-owner", "s", "k", "t7", later, now) is None
        assert db.sweep_keys(later + dt.timedelta(seconds=1)) == 3
        job = db.create("o", {}, "a.zip")
        assert db.reserve_key("o", "s", "j", "t8", later, now) is None
        assert db.finish_key("o", "s", "j", "t8", "f" * 64, job.id, 202)
        assert db.delete(job.id)
        assert db.reserve_key("o", "s", "j", "t9", later, now) is None  # the job's key went with it


# -- a real server: an upload cut off half way, and one whose answer was lost ---------------------------------------
@contextlib.contextmanager
def _raw_post(base_url: str, key: str, body: bytes, content_type: str, send: int) -> Iterator[socket.socket]:
    """POST /v1/jobs over a bare socket, sending the first ``send`` bytes of the body; the socket is closed, its
    answer never read, when the block ends."""
    where = urlsplit(base_url)
    head = (
        f"POST /v1/jobs HTTP/1.1\r\nHost: {where.netloc}\r\nX-API-Key: key-a\r\nIdempotency-Key: {key}\r\n"
        f"Content-Type: {content_type}\r\nContent-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    ).encode()
    with socket.create_connection((where.hostname or "127.0.0.1", where.port or 80), timeout=30) as sock:
        sock.sendall(head + body[:send])
        yield sock


def test_a_phone_retrying_an_upload_makes_one_job(make_stack: StackFactory) -> None:
    _, stack = make_stack(workers=0)
    request = httpx.Request(
        "POST",
        "http://x/v1/jobs",
        files={"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")},
        data={"params": json.dumps(HEADSQ.params)},
    )
    body, content_type = request.read(), request.headers["content-type"]
    with stack.client("key-a") as client:
        before = client.get("/v1/jobs").json()["total"]
        # the connection drops half way through the body: the server makes nothing, and gives the key up
        key = "phone-" + uuid.uuid4().hex
        with _raw_post(stack.base_url, key, body, content_type, len(body) // 2):
            time.sleep(0.3)
        time.sleep(0.5)
        retried = _upload(client, key, HEADSQ.params)
        assert retried.status_code == 202, retried.text
        assert idempotency.REPLAYED.lower() not in retried.headers
        assert client.get("/v1/jobs").json()["total"] == before + 1
        # the whole body arrives, the job is made, and the phone sends the upload again before the answer comes
        # (then the answer is lost): the job the first request made (409 while the first is being finished)
        key = "phone-" + uuid.uuid4().hex
        with _raw_post(stack.base_url, key, body, content_type, len(body)):
            wait_until(lambda: client.get("/v1/jobs").json()["total"] == before + 2, 30, "the first request's job")
            statuses: list[int] = []

            def replayed() -> httpx.Response | None:
                resp = _upload(client, key, HEADSQ.params)
                statuses.append(resp.status_code)
                if resp.status_code == 409:  # the first request is still being carried out: wait as told
                    assert resp.json()["code"] == "idempotency_key_in_use"
                    time.sleep(min(0.5, float(resp.headers["retry-after"])))
                    return None
                return resp

            again = wait_until(replayed, 60, "the retry of an upload whose answer was lost")
        assert again.status_code == 202, (statuses, again.text)
        assert again.headers[idempotency.REPLAYED] == "true", statuses
        assert client.get("/v1/jobs").json()["total"] == before + 2
        assert client.get(f"/v1/jobs/{again.json()['id']}").status_code == 200
