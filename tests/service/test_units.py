"""Service parts on their own: tokens, parameters, job claims, storage, upload checks, and the API's refusals
that need no broker (Redis is not running here: an accepted job stays queued for the reconciler)."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from core.db import Database, owner_of, utcnow
from core.params import JobParams
from core.storage import LocalStorage, UploadTooLarge
from engine.data import HEADSQ_ZIP
from engine.errors import InputError
from engine.io import inspect_input
from engine.params import ReconParams
from service import tokens
from tests.service.conftest import app_client


def test_tokens_open_one_file_until_they_expire() -> None:
    key = b"k" * 32
    token, expires = tokens.sign(key, "a" * 32, "model.stl", 60, now=1000.0)
    assert expires == 1060
    assert tokens.verify(key, token, now=1059.0) == ("a" * 32, "model.stl")
    with pytest.raises(tokens.BadToken, match="expired"):
        tokens.verify(key, token, now=1061.0)
    with pytest.raises(tokens.BadToken, match="signature"):
        tokens.verify(b"x" * 32, token, now=1000.0)
    sig = token.split(".")[1]
    forged, _ = tokens.sign(b"x" * 32, "a" * 32, "phone.glb", 60, now=1000.0)
    with pytest.raises(tokens.BadToken):
        tokens.verify(key, f"{forged.split('.')[0]}.{sig}", now=1000.0)
    with pytest.raises(tokens.BadToken, match="malformed"):
        tokens.verify(key, "not-a-token", now=1000.0)


def test_job_params_validate_and_become_engine_params() -> None:
    p = JobParams.model_validate({"preset": "bone", "hu_offset": 1024, "spacing": [1.5, 0.9, 0.9], "reduction": 0.3})
    recon = p.job_spec().recon
    assert recon.iso.preset == "bone" and recon.iso.hu_offset == 1024
    assert recon.decimate is not None and recon.decimate.reduction == 0.3
    assert recon.smooth is not None and recon.smooth.iterations == 1 and recon.smooth.angle_deg == 0.5
    capped = JobParams(max_triangles=5000).job_spec().recon
    assert capped.decimate is not None and (capped.decimate.reduction, capped.decimate.max_triangles) == (None, 5000)
    for bad in (
        {"iso": 1, "preset": "bone"},
        {"reduction": 0},
        {"reduction": 0.5, "max_triangles": 100},
        {"spacing": [1, 2]},
        {"spacing": [1, 0, 1]},
        {"preset": "marrow"},
        {"iterations": 0},
        {"angle": 90},
        {"colour": "red"},
    ):
        with pytest.raises(ValueError):
            JobParams.model_validate(bad)


def test_a_job_is_claimed_once_and_reclaimed_only_when_its_worker_is_silent(db_url: str) -> None:
    with contextlib.closing(Database(db_url)) as db:
        job = db.create(owner_of("key"), {}, "scan.zip")
        now = utcnow()
        first = db.claim(job.id, "w1", stale_before=now - dt.timedelta(seconds=60))
        assert first is not None and first.state == "running" and first.attempts == 1
        assert db.claim(job.id, "w2", stale_before=now - dt.timedelta(seconds=60)) is None  # w1 is alive
        assert db.beat(job.id, "w1", stage="decimate", progress=50.0)
        # w1 goes silent: once its heartbeat is older than the staleness limit, another worker may take over
        second = db.claim(job.id, "w2", stale_before=utcnow() + dt.timedelta(seconds=1))
        assert second is not None and second.attempts == 2 and second.worker == "w2"
        assert not db.beat(job.id, "w1")  # the old holder learns it lost the job...
        assert not db.finish(job.id, "w1", "succeeded")  # ...and cannot record a result
        assert db.finish(job.id, "w2", "succeeded", outputs=[])
        assert db.claim(job.id, "w3", stale_before=utcnow() + dt.timedelta(seconds=1)) is None  # finished: never again
        other = db.create(owner_of("key"), {}, "b.zip")
        assert db.cancel(other.id) and not db.cancel(other.id)
        assert db.claim(other.id, "w1", stale_before=utcnow()) is None
        assert db.get(other.id, owner_of("someone else")) is None
        rows, total = db.list(owner_of("key"), limit=1, offset=0)
        assert total == 2 and [r.id for r in rows] == [other.id]


def test_storage_never_shows_a_partial_file(tmp_path: Path) -> None:
    store = LocalStorage(tmp_path)
    job = "b" * 32
    w = store.upload_writer(job, max_bytes=10)
    w.write(b"12345")
    with pytest.raises(UploadTooLarge):
        w.write(b"678901")
    assert not store.upload_path(job).exists() and not any((tmp_path / "jobs" / job).iterdir())
    w = store.upload_writer(job, max_bytes=10)
    w.write(b"abc")
    assert not store.upload_path(job).exists()  # not before commit
    w.commit()
    assert store.upload_path(job).read_bytes() == b"abc"
    staged = store.staging_dir(job)
    (staged / "model.stl").write_bytes(b"one")
    assert store.output_path(job, "model.stl") is None  # staged is not published
    store.publish(job, staged)
    again = store.staging_dir(job)
    (again / "model.stl").write_bytes(b"two")
    (again / "notes.txt").write_bytes(b"not an output")
    store.publish(job, again)
    path = store.output_path(job, "model.stl")
    assert path is not None and path.read_bytes() == b"two"
    assert store.output_path(job, "../upload") is None
    assert store.output_path(job, "notes.txt") is None  # published, but not a file of the registry
    with pytest.raises(ValueError):
        store.upload_path("../../etc")
    store.delete_job(job)
    assert store.output_path(job, "model.stl") is None


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def test_inspect_input_sees_what_an_upload_holds(tmp_path: Path) -> None:
    summary = inspect_input(HEADSQ_ZIP)
    assert summary.kind == "zip" and summary.images == 93 and summary.dicom == 0
    cases = {
        "text.bin": (b"hello, not a scan", "neither an archive"),
        "notes.zip": (_zip({"notes.txt": b"no images here"}), "no image slices"),
        "evil.zip": (_zip({"../../evil.png": b"\x89PNG\r\n\x1a\n"}), "outside the archive"),
        "bomb.zip": (_zip({"a.png": b"\x89PNG\r\n\x1a\n" + bytes(300 << 20)}), "zip bomb"),
    }
    for name, (data, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(InputError, match=message):
            inspect_input(path)


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with app_client(tmp_path, max_upload_bytes=2 << 20) as c:  # a small cap for the 413 tests
        yield c


def _post(client: TestClient, key: str | None, data: bytes, params: object = None) -> object:
    files = {"file": ("scan.zip", data, "application/zip")}
    form = {} if params is None else {"params": params if isinstance(params, str) else json.dumps(params)}
    headers = {} if key is None else {"X-API-Key": key}
    return client.post("/v1/jobs", files=files, data=form, headers=headers)


def test_api_refusals_are_problems_with_reasons(client: TestClient) -> None:
    scan = HEADSQ_ZIP.read_bytes()
    r = _post(client, None, scan)
    assert r.status_code == 401 and r.headers["content-type"] == "application/problem+json"
    assert _post(client, "wrong", scan).status_code == 401
    r = _post(client, "key-a", scan, {"reduction": 1.5})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "params.reduction"
    r = _post(client, "key-a", scan, "{not json")
    assert r.status_code == 422 and "JSON" in r.json()["detail"]
    r = _post(client, "key-a", b"plain text, not an archive")
    assert r.status_code == 415 and "scan.zip" in r.json()["detail"]
    r = _post(client, "key-a", _zip({"readme.txt": b"hi"}))
    assert r.status_code == 422 and "no image slices" in r.json()["detail"]
    r = _post(client, "key-a", bytes(3 << 20))  # refused on its Content-Length
    assert r.status_code == 413
    r = _post(client, "key-a", bytes((2 << 20) + 4096))  # within the header slack: refused while streaming
    assert r.status_code == 413 and "limit" in r.json()["detail"]
    r = client.post("/v1/jobs", content=b"x", headers={"X-API-Key": "key-a", "Content-Type": "application/zip"})
    assert r.status_code == 415
    r = client.post("/v1/jobs", files={"other": ("a", b"b")}, headers={"X-API-Key": "key-a"})
    assert r.status_code == 422
    r = client.get("/v1/files/forged.token")
    assert r.status_code == 403
    jobs = Path(client.app.state.data_dir) / "jobs"
    assert not [p for p in jobs.rglob("*") if p.is_file()], "a refused upload left files behind"


def test_accepted_job_is_private_to_its_key_and_stays_queued_without_broker(client: TestClient) -> None:
    r = _post(client, "key-a", HEADSQ_ZIP.read_bytes(), {"iso": 1150, "spacing": [1.5, 3.2, 3.2]})
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["state"] == "queued" and job["upload_bytes"] == HEADSQ_ZIP.stat().st_size and job["outputs"] is None
    assert client.get(f"/v1/jobs/{job['id']}", headers={"X-API-Key": "key-b"}).status_code == 404
    listed = client.get("/v1/jobs", headers={"X-API-Key": "key-a"}).json()
    assert listed["total"] == 1 and listed["items"][0]["id"] == job["id"]
    assert client.get("/v1/jobs", headers={"X-API-Key": "key-b"}).json()["total"] == 0
    assert client.delete(f"/v1/jobs/{job['id']}", headers={"X-API-Key": "key-b"}).status_code == 404
    assert client.post(f"/v1/jobs/{job['id']}/cancel", headers={"X-API-Key": "key-b"}).status_code == 404
    cancelled = client.post(f"/v1/jobs/{job['id']}/cancel", headers={"X-API-Key": "key-a"})
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    assert client.get(f"/v1/jobs/{job['id']}", headers={"X-API-Key": "key-a"}).json()["state"] == "cancelled"
    assert client.delete(f"/v1/jobs/{job['id']}", headers={"X-API-Key": "key-a"}).status_code == 204
    assert client.get(f"/v1/jobs/{job['id']}", headers={"X-API-Key": "key-a"}).status_code == 404
    ready = client.get("/readyz")
    assert ready.status_code == 503 and ready.json()["checks"]["redis"].startswith("unreachable")


def test_a_new_database_switched_to_wal_by_another_process_is_waited_for(tmp_path: Path) -> None:
    """Processes starting together on a new SQLite database all switch it to WAL; SQLite answers one of two such
    switches "locked" at once (no busy wait), which stopped an API process at start-up. The switch is retried."""
    import sqlite3
    import threading

    from core.db import _sqlite_pragmas

    path = tmp_path / "jobs.db"
    other = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    other.execute("CREATE TABLE t (a)")
    other.execute("BEGIN EXCLUSIVE")  # as another process in the middle of its own switch
    threading.Timer(0.5, lambda: other.execute("COMMIT")).start()
    conn = sqlite3.connect(path, timeout=0, check_same_thread=False)  # no busy wait: the retry is what waits
    _sqlite_pragmas(conn, None)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.close()
    other.close()
