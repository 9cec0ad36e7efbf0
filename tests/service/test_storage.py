"""The storage contract, on both backends: local disk and a real S3 store (SeaweedFS, ``seaweed_server``).

Uploads stream in and are seen only once committed (a refused or aborted one leaves nothing, on S3 no pending
multipart upload either); the worker's copy of the input is removed after use, also on failure; outputs are
published as a version that readers name (on S3 a new version is invisible to a reader of the committed one until
the record moves on); deleting a job deletes its objects; presigned links download the right bytes and type, and
expire. And no message a client reads carries a server path.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from core.s3storage import PART_BYTES, S3Storage
from core.storage import LocalStorage, Storage, UploadTooLarge, scrub_paths
from engine.export.files import FILES
from tests.service.seaweed import REGION, SeaweedServer

JOB = "c" * 32


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Storage]:
    """A fresh storage: a local folder, or a new bucket (under a prefix) on the session's SeaweedFS."""
    if request.param == "local":
        yield LocalStorage(tmp_path / "data")
        return
    s3: SeaweedServer = request.getfixturevalue("seaweed_server")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", s3.access_key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", s3.secret_key)
    monkeypatch.setenv("AWS_DEFAULT_REGION", REGION)
    yield S3Storage(s3.make_bucket(), "tenant/bonemesh", endpoint_url=s3.endpoint, scratch=tmp_path / "scratch")


def keys(store: Storage, job_id: str = JOB) -> list[str]:
    """Every object (S3) or file (local) a job has."""
    if isinstance(store, S3Storage):
        return [o["Key"] for o in store._keys(store._job(job_id) + "/")]
    folder = store.root / "jobs" / job_id
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def pending_uploads(store: Storage) -> list[Any]:
    """Multipart uploads begun and neither completed nor aborted (S3 only)."""
    if not isinstance(store, S3Storage):
        return []
    return store.client.list_multipart_uploads(Bucket=store.bucket).get("Uploads", [])


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def stage(store: Storage, files: dict[str, bytes], job_id: str = JOB) -> Path:
    staged = store.staging_dir(job_id)
    for name, data in files.items():
        (staged / name).write_bytes(data)
    return staged


def test_upload_streams_in_and_shows_only_once_committed(store: Storage) -> None:
    data = os.urandom(2 * PART_BYTES + 12345)  # three parts on S3: two full, one short
    writer = store.upload_writer(JOB, max_bytes=len(data))
    for i in range(0, len(data), 3 << 20):  # the API hands over batches of a few MiB
        writer.write(memoryview(data)[i : i + (3 << 20)])
    assert not store.has_upload(JOB)  # not before commit
    writer.commit()
    assert store.has_upload(JOB) and writer.size == len(data) and not pending_uploads(store)
    with store.local_upload(JOB) as path:
        assert hashlib.sha256(path.read_bytes()).digest() == hashlib.sha256(data).digest()


def test_a_local_upload_is_handed_to_the_disk_as_it_arrives(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ``WRITEBACK_BYTES`` the bytes written so far start on their way to the disk (each range once, in
    order, flushed first: the fsync at commit then waits for the last range only), and the upload is the same."""
    import core.storage as storage

    ranges: list[tuple[int, int, int]] = []

    def record(fd: int, offset: int, length: int) -> None:
        ranges.append((offset, length, os.fstat(fd).st_size))
        real(fd, offset, length)  # the real call on the real file: Linux's sync_file_range, elsewhere nothing

    real = storage.start_writeback
    monkeypatch.setattr(storage, "WRITEBACK_BYTES", 1 << 20)
    monkeypatch.setattr(storage, "start_writeback", record)
    store = LocalStorage(tmp_path)
    data = os.urandom((7 << 20) // 2 + 5)
    writer = store.upload_writer(JOB, max_bytes=len(data))
    for i in range(0, len(data), 300_000):
        writer.write(memoryview(data)[i : i + 300_000])
    writer.commit()
    assert [r[0] for r in ranges] == [sum(r[1] for r in ranges[:k]) for k in range(len(ranges))]  # in order, once
    assert len(ranges) == 3 and all(length >= 1 << 20 and size == off + length for off, length, size in ranges)
    with store.local_upload(JOB) as path:
        assert path.read_bytes() == data


def test_a_local_upload_written_in_batches_survives_short_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A batch goes to the file in one ``writev`` where it can; where the system writes less (here at most 7 bytes
    a call, at most 3 buffers), the rest follows in order. Over the limit, nothing is kept."""
    import core.storage as storage

    real = os.writev
    calls: list[int] = []

    def short(fd: int, buffers: list[memoryview]) -> int:
        calls.append(len(buffers))
        return real(fd, [bytes(b"".join(bytes(b) for b in buffers[:3])[:7])])

    monkeypatch.setattr(storage.os, "writev", short)
    store = LocalStorage(tmp_path)
    data = os.urandom(1000)
    writer = store.upload_writer(JOB, max_bytes=len(data))
    writer.write(memoryview(data)[:10])  # a single write first: its buffered bytes go before the batch
    writer.write_many([memoryview(data)[i : i + 33] for i in range(10, 1000, 33)])
    writer.commit()
    assert writer.size == len(data) and len(calls) > 100 and max(calls) > 3
    with store.local_upload(JOB) as path:
        assert path.read_bytes() == data
    too_big = store.upload_writer(JOB, max_bytes=10)
    with pytest.raises(UploadTooLarge):
        too_big.write_many([memoryview(b"x" * 6), memoryview(b"y" * 6)])
    assert not list(tmp_path.rglob(".upload-*.part"))  # the refused one left nothing; the earlier upload stays
    with store.local_upload(JOB) as path:
        assert path.read_bytes() == data


def test_a_refused_or_aborted_upload_leaves_nothing(store: Storage) -> None:
    writer = store.upload_writer(JOB, max_bytes=PART_BYTES + 10)
    writer.write(os.urandom(PART_BYTES))  # a part is on its way (S3)
    with pytest.raises(UploadTooLarge):
        writer.write(b"x" * 11)
    assert not store.has_upload(JOB) and not pending_uploads(store)
    writer = store.upload_writer(JOB, max_bytes=1 << 30)
    writer.write(os.urandom(PART_BYTES + 1))
    writer.abort()
    assert not store.has_upload(JOB) and not pending_uploads(store)
    small = store.upload_writer(JOB, max_bytes=10)  # under one part: a single PUT at commit on S3
    small.write(b"abc")
    small.commit()
    with store.local_upload(JOB) as path:
        assert path.read_bytes() == b"abc"


def test_the_input_copy_is_removed_after_use_also_on_failure(store: Storage, tmp_path: Path) -> None:
    writer = store.upload_writer(JOB, max_bytes=100)
    writer.write(b"scan bytes")
    writer.commit()
    with pytest.raises(RuntimeError), store.local_upload(JOB) as path:
        seen = path
        assert path.read_bytes() == b"scan bytes"
        raise RuntimeError("the pipeline failed")
    if isinstance(store, S3Storage):
        assert not seen.exists() and not any(store.scratch.iterdir())
    else:
        assert seen.exists()  # local disk: the upload itself, read in place
    assert store.has_upload(JOB)


def test_a_received_series_folder_becomes_the_upload_or_goes_back(store: Storage, tmp_path: Path) -> None:
    def series(folder: Path) -> Path:
        (folder / "sub").mkdir(parents=True)
        (folder / "1.dcm").write_bytes(b"one")
        (folder / "sub" / "2.dcm").write_bytes(b"two")
        return folder

    folder = series(tmp_path / "series-a")
    with pytest.raises(RuntimeError), store.put_upload_folder(JOB, folder):
        raise RuntimeError("the record could not be written")
    assert (folder / "sub" / "2.dcm").read_bytes() == b"two" and not store.has_upload(JOB)  # back, nothing kept
    with store.put_upload_folder(JOB, folder):
        pass
    assert not folder.exists() and store.has_upload(JOB)
    with store.local_upload(JOB) as path:
        assert sorted(str(p.relative_to(path)) for p in path.rglob("*") if p.is_file()) == ["1.dcm", "sub/2.dcm"]
        assert (path / "sub" / "2.dcm").read_bytes() == b"two"


def test_outputs_are_published_as_a_version_readers_name(store: Storage, tmp_path: Path) -> None:
    staged = stage(store, {"model.stl": b"one", "report.json": b'{"v": 1}'})
    assert store.output(JOB, "model.stl") is None  # staged is not published
    first = store.publish(JOB, staged)
    assert not staged.exists()
    got = store.output(JOB, "model.stl", first)
    assert got is not None and got.size == 3 and store.read_output(JOB, "report.json", first) == b'{"v": 1}'
    second = store.publish(JOB, stage(store, {"model.stl": b"two!", "notes.txt": b"not an output"}))
    assert second != first
    assert store.read_output(JOB, "model.stl", second) == b"two!"
    assert b"".join(store.open_output(JOB, "model.stl", second)) == b"two!"
    assert store.output(JOB, "notes.txt", second) is None and store.output(JOB, "../upload", second) is None
    if isinstance(store, S3Storage):  # until the record names the new version, its readers see the old one whole
        assert store.read_output(JOB, "model.stl", first) == b"one"
        assert store.read_output(JOB, "report.json", first) == b'{"v": 1}'
        assert store.read_output(JOB, "report.json", second) is None
    store.retire(JOB, keep=second)
    if isinstance(store, S3Storage):
        assert store.read_output(JOB, "model.stl", first) is None
        assert all(f"/outputs/{second}/" in k for k in keys(store))
    into = tmp_path / "copy"
    into.mkdir()
    assert store.copy_outputs(JOB, second, into) == ["model.stl"] and (into / "model.stl").read_bytes() == b"two!"
    with store.local_output(JOB, "model.stl", second) as path:
        assert path is not None and path.read_bytes() == b"two!"
        seen = path
    assert seen.exists() == (not isinstance(store, S3Storage))  # a scratch copy off local disk, removed after
    with store.local_output(JOB, "model.glb", second) as missing:
        assert missing is None


def _killed_publish(store: Storage, job_id: str) -> str:
    """What a publish killed half way leaves: on S3 a part of a large output's multipart upload, never completed
    (the object invisible), on local disk the replaced outputs folder between the two renames."""
    version = "f" * 32
    if isinstance(store, S3Storage):
        key = f"{store._job(job_id)}/outputs/{version}/model.stl"
        up = store.client.create_multipart_upload(Bucket=store.bucket, Key=key)["UploadId"]
        store.client.upload_part(Bucket=store.bucket, Key=key, UploadId=up, PartNumber=1, Body=b"x" * PART_BYTES)
    else:
        old = store.root / "jobs" / job_id / f".old-{version}"
        old.mkdir(parents=True)
        (old / "model.stl").write_bytes(b"half")
    return version


def test_what_a_killed_publish_left_goes_with_the_next_attempt_or_the_sweep(store: Storage) -> None:
    import datetime as dt

    _killed_publish(store, JOB)
    other = "e" * 32
    _killed_publish(store, other)
    version = store.publish(JOB, stage(store, {"model.stl": b"whole"}))  # the next attempt
    store.retire(JOB, keep=version)
    s3 = isinstance(store, S3Storage)
    assert [u["Key"].split("/")[-4] for u in pending_uploads(store)] == ([other] if s3 else [])
    now = dt.datetime.now(dt.UTC)
    assert store.sweep_outputs(now - dt.timedelta(hours=1)) == 0  # too young: may belong to a live attempt
    assert store.sweep_outputs(now + dt.timedelta(seconds=5)) == (1 if s3 else 2)  # local: retire keeps its folder
    assert pending_uploads(store) == [] and store.read_output(JOB, "model.stl", version) == b"whole"
    assert s3 or not list((store.root / "jobs").glob("*/.old-*"))


def test_deleting_a_job_deletes_its_objects(store: Storage) -> None:
    other = "d" * 32
    for job_id in (JOB, other):
        writer = store.upload_writer(job_id, max_bytes=1 << 30)
        writer.write(b"scan")
        writer.commit()
        store.publish(job_id, stage(store, {"model.stl": b"solid", "model.glb": b"glb"}, job_id))
    pending = store.upload_writer(JOB, max_bytes=1 << 30)
    pending.write(os.urandom(PART_BYTES + 1))  # an upload still coming in (S3: a multipart upload begun)
    assert keys(store)
    store.delete_job(JOB)
    assert keys(store) == [] and not store.has_upload(JOB) and not pending_uploads(store)
    assert len(keys(store, other)) >= 3  # the other job's files stay
    pending.abort()  # the upload's request ends (the API discards it): nothing comes back
    assert keys(store) == [] and not pending_uploads(store)


def test_presigned_links_download_the_right_bytes_and_expire(store: Storage) -> None:
    version = store.publish(JOB, stage(store, {"model.stl": b"solid bone", "model.glb": b"glTF..."}))
    if not isinstance(store, S3Storage):
        assert not store.presigns and store.output_url(JOB, "model.stl", version, 60) is None
        return
    for name, data in (("model.stl", b"solid bone"), ("model.glb", b"glTF...")):
        url = store.output_url(JOB, name, version, 60)
        assert url is not None and "X-Amz-Signature=" in url and "X-Amz-Expires=60" in url
        resp = httpx.get(url, timeout=30)  # no credentials: the link alone
        assert resp.status_code == 200 and resp.content == data
        assert resp.headers["content-type"] == FILES[name].media_type
        assert f'filename="{name}"' in resp.headers["content-disposition"]
    assert httpx.get(url.replace("X-Amz-Signature=", "X-Amz-Signature=0"), timeout=30).status_code == 403
    short = store.output_url(JOB, "model.stl", version, 1)
    assert short is not None
    time.sleep(2.2)
    assert httpx.get(short, timeout=30).status_code == 403  # expired


def test_server_paths_are_hidden_from_messages(tmp_path: Path) -> None:
    upload = tmp_path / "data" / "jobs" / JOB / "upload"
    labels = {str(upload): "upload", str(tmp_path / "scratch"): "the worker's scratch folder"}
    assert scrub_paths(f"{upload} does not exist (expected a zip)", labels) == "upload does not exist (expected a zip)"
    shown = scrub_paths(f"cannot read {upload}/slices/x.png; {tmp_path}/scratch/{JOB}-input-1/upload", labels)
    assert str(tmp_path) not in shown and "/jobs/" not in shown
    assert scrub_paths(f"member /srv/other/jobs/{JOB}/outputs/model.stl failed", {}) == (
        "member the job's files failed"
    )


def test_a_failed_job_tells_no_server_path(
    store: Storage, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest
) -> None:
    """The real worker task on a job whose upload is gone: "bad_input" naming the client's file, not a path."""
    from core.db import Database, owner_of
    from core.settings import Settings
    from worker import tasks

    env: dict[str, Any] = {"data_dir": tmp_path / "data", "database_url": f"sqlite:///{tmp_path / 'jobs.db'}"}
    if isinstance(store, S3Storage):
        s3: SeaweedServer = request.getfixturevalue("seaweed_server")
        env |= {"storage_url": f"s3://{store.bucket}/{store.prefix}", "s3_endpoint_url": s3.endpoint}
        env |= {"scratch_dir": store.scratch}
    settings = Settings(**env)
    monkeypatch.setattr(tasks, "get_settings", lambda: settings)
    db = Database(settings.db_url)
    try:
        job = db.create(owner_of("k"), {}, "scan of Jane.zip", 10, engine_params={"recon": {}, "spacing_zyx_mm": None})
        assert tasks.reconstruct_job(job.id) == "failed"
        done = db.get(job.id)
        assert done is not None and done.error_code == "bad_input", (done.error_code, done.error_message)
        message = done.error_message or ""
        assert message.startswith("scan of Jane.zip does not exist"), message
        assert str(tmp_path) not in message and "/jobs/" not in message and "scratch" not in message
        if isinstance(store, S3Storage):
            assert not any(store.scratch.iterdir())  # the worker's scratch copy and staging are gone
    finally:
        db.close()


def test_create_bucket_makes_the_storage_urls_bucket_once(
    request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``python -m core.s3storage create-bucket`` (docker-compose's ``s3-init``): made, then found; a file URL is
    refused."""
    import uuid

    from core.s3storage import create_bucket
    from core.settings import Settings

    s3: SeaweedServer = request.getfixturevalue("seaweed_server")
    for name, value in s3.env("unused").items():
        monkeypatch.setenv(name, value)
    bucket = f"made-{uuid.uuid4().hex[:10]}"
    settings = Settings(storage_url=f"s3://{bucket}/jobs", s3_endpoint_url=s3.endpoint, data_dir=tmp_path)
    assert create_bucket(settings) == f"bucket {bucket} made"
    assert create_bucket(settings) == f"bucket {bucket} exists"
    s3.client().head_bucket(Bucket=bucket)
    with pytest.raises(ValueError, match="not an s3:// URL"):
        create_bucket(Settings(storage_url=f"file://{tmp_path}", data_dir=tmp_path))
