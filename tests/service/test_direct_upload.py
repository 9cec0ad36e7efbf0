"""Direct uploads with real processes: a redis-server, ``bonemesh serve`` and a ``bonemesh worker`` on a real S3
store (SeaweedFS). The client begins an upload, PUTs the parts straight to the store through the presigned links
(with a Content-Type of its own, which the signature does not cover), completes it, and the job runs; the API
never carries the scan. Missing parts leave the upload open, a wrong ETag or a non-archive is refused and leaves
nothing; aborting drops every part; an upload left incomplete is aborted by the API's sweep, as is a multipart
upload no record explains. With local storage the routes answer 409 and the options say why.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import httpx
import pytest

from tests.service.checks import assert_problem, check_outputs
from tests.service.conftest import HEADSQ, StackFactory
from tests.service.procs import ServiceStack, wait_for_job, wait_until
from tests.service.seaweed import SeaweedServer

PREFIX = "direct"


class S3Stack:
    """One stack on a bucket of its own: ``api`` (uploads expire in a day) and ``sweeper`` (a second API process
    whose uploads expire in 2 s, sweeping every second), one worker."""

    def __init__(self, stack: ServiceStack, s3: SeaweedServer, bucket: str, sweeper: str) -> None:
        self.stack, self.s3, self.bucket, self.sweeper = stack, s3, bucket, sweeper

    def objects(self, job_id: str) -> list[str]:
        listed = self.s3.client().list_objects_v2(Bucket=self.bucket, Prefix=f"{PREFIX}/jobs/{job_id}/")
        return [o["Key"] for o in listed.get("Contents", [])]

    def pending(self) -> list[dict[str, Any]]:
        return self.s3.client().list_multipart_uploads(Bucket=self.bucket).get("Uploads", [])


@pytest.fixture(scope="module")
def s3_stack(seaweed_server: SeaweedServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Stack]:
    factory = StackFactory(tmp_path_factory.mktemp("direct"))
    try:
        bucket = seaweed_server.make_bucket()
        _, stack = factory(server=False, workers=0, extra_env=seaweed_server.env(bucket, PREFIX))
        stack.start_server()
        sweeper = stack.start_server(extra_env={"BONEMESH_UPLOAD_TTL_SECONDS": "2"})
        stack.start_worker(extra_env={"BONEMESH_DATA_DIR": str(stack.root / "worker-data")})
        yield S3Stack(stack, seaweed_server, bucket, sweeper)
    finally:
        factory.close()


def begin(client: httpx.Client, name: str, size: int, **extra: Any) -> dict[str, Any]:
    resp = client.post("/v1/uploads", json={"filename": name, "size": size, **extra})
    assert resp.status_code == 201, resp.text
    assert resp.headers["location"] == f"/v1/uploads/{resp.json()['id']}"
    return resp.json()  # type: ignore[no-any-return]


def put_part(part: dict[str, Any], data: bytes) -> str:
    """PUT one part as a client would: its own Content-Type added (not signed, so harmless); returns the ETag."""
    body = data[part["offset"] : part["offset"] + part["bytes"]]
    resp = httpx.put(part["url"], content=body, headers={**part["headers"], "Content-Type": "application/zip"})
    assert resp.status_code == 200, resp.text
    return resp.headers["etag"]


def test_options_say_direct_and_the_links_sign_only_host(s3_stack: S3Stack) -> None:
    with s3_stack.stack.client() as client:
        options = client.get("/v1/upload-options").json()
        assert options["direct"] is True and options["reason"] is None and options["parallel_parts"] == 4
        size = 20 << 20  # three parts: 8 + 8 + 4 MiB
        up = begin(client, "big.zip", size)
        assert up["part_bytes"] == 8 << 20 and [p["bytes"] for p in up["parts"]] == [8 << 20, 8 << 20, 4 << 20]
        for part in up["parts"]:
            query = parse_qs(urlsplit(part["url"]).query)
            assert query["X-Amz-SignedHeaders"] == ["host"] and query["partNumber"] == [str(part["number"])]
            assert query["X-Amz-Algorithm"] == ["AWS4-HMAC-SHA256"] and part["headers"] == {}
            assert part["url"].startswith(f"{s3_stack.s3.endpoint}/{s3_stack.bucket}/{PREFIX}/jobs/{up['id']}/upload?")
        assert client.delete(up["abort_url"]).status_code == 204
        assert not s3_stack.pending()
        assert_problem(client.post(up["complete_url"], json={}), 404)


def test_a_direct_upload_becomes_a_job_that_runs(s3_stack: S3Stack) -> None:
    data = HEADSQ.path.read_bytes()
    with s3_stack.stack.client() as client, httpx.Client(timeout=60) as anon:
        up = begin(client, "headsq.zip", len(data), params=HEADSQ.params)
        (part,) = up["parts"]
        etag = put_part(part, data)
        with s3_stack.stack.client("key-b") as other:  # another key neither sees nor completes it
            assert_problem(other.post(up["complete_url"], json={}), 404)
        resp = client.post(up["complete_url"], json={"parts": [{"number": 1, "etag": etag}]})
        assert resp.status_code == 202, resp.text
        job = resp.json()
        assert job["id"] == up["id"] and job["upload_name"] == "headsq.zip" and job["upload_bytes"] == len(data)
        assert resp.headers["location"] == f"/v1/jobs/{job['id']}"
        again = client.post(up["complete_url"], json={})  # the answer lost, sent again: the same job, not a second
        assert again.status_code == 202 and again.json()["id"] == job["id"], again.text
        assert again.headers["idempotent-replayed"] == "true" and again.headers["location"] == resp.headers["location"]
        with s3_stack.stack.client("key-b") as other:  # another key's completion still finds nothing
            assert_problem(other.post(up["complete_url"], json={}), 404)
        job = wait_for_job(client, job["id"], stack=s3_stack.stack, timeout=300)
        assert job["state"] == "succeeded", job
        ((run,),) = [job["runs"]]
        assert run["outcome"] == "succeeded" and run["host"] and run["worker"].startswith("bonemesh@"), run
        check_outputs(anon, {o["name"]: o for o in job["outputs"]}, HEADSQ.shape_zyx, HEADSQ.spacing_zyx_mm)
        assert f"{PREFIX}/jobs/{job['id']}/upload" in s3_stack.objects(job["id"])
        assert not s3_stack.pending()


def test_missing_parts_keep_it_open_and_a_non_scan_leaves_nothing(s3_stack: S3Stack) -> None:
    data = os.urandom((8 << 20) + 4321)  # two parts; not an archive
    with s3_stack.stack.client() as client:
        up = begin(client, "noise.zip", len(data), params={"iso": 100})
        first, second = up["parts"]
        etag = put_part(first, data)
        short = assert_problem(client.post(up["complete_url"], json={}), 422)
        assert "parts 2 not received" in short["detail"] and short["code"] == "upload_incomplete", short
        wrong = {"parts": [{"number": 1, "etag": etag}, {"number": 2, "etag": '"0123"'}]}
        put_part(second, data)
        assert "ETags do not match" in assert_problem(client.post(up["complete_url"], json=wrong), 422)["detail"]
        refused = assert_problem(client.post(up["complete_url"], json={}), (415, 422))  # the archive check
        assert str(s3_stack.stack.root) not in refused["detail"] and "scratch" not in refused["detail"], refused
        assert not s3_stack.objects(up["id"]) and not s3_stack.pending()
        assert_problem(client.get(f"/v1/jobs/{up['id']}"), 404)


def test_what_a_direct_upload_refuses(s3_stack: S3Stack) -> None:
    with s3_stack.stack.client() as client:
        too_big = client.post("/v1/uploads", json={"filename": "x.zip", "size": (64 << 20) + 1})
        assert "over the limit" in assert_problem(too_big, 413)["detail"]
        bad = client.post("/v1/uploads", json={"filename": "x.zip", "size": 10, "params": {"iso": "high"}})
        assert assert_problem(bad, 422)["errors"][0]["field"].startswith("body.params.iso")
        hook = client.post("/v1/uploads", json={"filename": "x.zip", "size": 10, "callback_url": "ftp://x/y"})
        assert assert_problem(hook, 422)["errors"][0]["field"] == "callback_url"
        assert_problem(client.post("/v1/uploads", json={"filename": "x.zip", "size": 0}), 422)
        assert_problem(client.delete(f"/v1/uploads/{'f' * 32}"), 404)
    assert not s3_stack.pending()


def test_the_sweep_aborts_what_is_left(s3_stack: S3Stack) -> None:
    data = os.urandom(1000)
    with s3_stack.stack.client(base_url=s3_stack.sweeper) as client:
        up = begin(client, "left.zip", len(data))
        put_part(up["parts"][0], data)
        orphan_key = f"{PREFIX}/jobs/{'e' * 32}/upload"  # an upload begun by an API process killed at once
        s3 = s3_stack.s3.client()
        s3.create_multipart_upload(Bucket=s3_stack.bucket, Key=orphan_key)
        assert len(s3_stack.pending()) == 2
        wait_until(lambda: not s3_stack.pending(), 30, "the sweep to abort both uploads", interval=0.5)
        assert_problem(client.post(up["complete_url"], json={}), 404)
        assert not s3_stack.objects(up["id"])


@pytest.fixture
def local_client(tmp_path: Path) -> Iterator[Any]:
    from tests.service.conftest import app_client

    with app_client(tmp_path) as c:
        yield c


def test_local_storage_says_no_direct_upload(local_client: Any) -> None:
    keyed = {"X-API-Key": "key-a"}
    options = local_client.get("/v1/upload-options", headers=keyed).json()
    assert options["direct"] is False and "POST /v1/jobs" in options["reason"]
    for method, path, body in (
        ("POST", "/v1/uploads", {"filename": "a.zip", "size": 10}),
        ("POST", f"/v1/uploads/{'a' * 32}/complete", {}),
        ("DELETE", f"/v1/uploads/{'a' * 32}", None),
    ):
        resp = local_client.request(method, path, json=body, headers=keyed)
        assert resp.status_code == 409 and "POST /v1/jobs" in resp.json()["detail"], resp.text
    assert local_client.get("/v1/upload-options").status_code == 401


@pytest.mark.browser
def test_the_page_uploads_straight_to_the_store(s3_stack: S3Stack, tmp_path: Path) -> None:
    """The page sees S3 storage, sends the parts to the store (4 at a time, with progress), and the job runs; a
    scan the API refuses after the parts arrived is reported, and the store keeps nothing of it."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    from tests.service.browser import find_chromium, start_chromium

    paths = find_chromium()
    if isinstance(paths, str):
        pytest.skip(paths)
    noise = tmp_path / "noise.zip"
    noise.write_bytes(os.urandom((16 << 20) + 777))  # three parts, and no archive
    driver = start_chromium(*paths, tmp_path)
    try:
        driver.get(s3_stack.stack.base_url + "/")
        driver.find_element(By.ID, "api-key").send_keys("key-a")
        driver.find_element(By.ID, "key-save").click()
        file_input = driver.find_element(By.ID, "file-input")
        driver.execute_script("arguments[0].hidden = false", file_input)
        text = lambda: driver.find_element(By.ID, "upload-text").text  # noqa: E731

        file_input.send_keys(str(noise))
        wait_until(lambda: "noise.zip" in driver.find_element(By.ID, "picked").text, 10, "the file to be picked")
        driver.find_element(By.ID, "start").click()
        wait_until(lambda: text().startswith("refused:"), 60, "the refusal")
        via = driver.find_element(By.ID, "upload-progress").get_attribute("data-via")
        assert via == "store" and not s3_stack.pending(), (via, text())

        driver.refresh()
        file_input = driver.find_element(By.ID, "file-input")
        driver.execute_script("arguments[0].hidden = false", file_input)
        file_input.send_keys(str(HEADSQ.path))
        wait_until(lambda: "headsq" in driver.find_element(By.ID, "picked").text, 10, "the file to be picked")
        Select(driver.find_element(By.ID, "level-kind")).select_by_value("iso")
        driver.find_element(By.ID, "iso").send_keys(str(HEADSQ.params["iso"]))
        driver.find_element(By.ID, "spacing").send_keys(", ".join(str(v) for v in HEADSQ.params["spacing"]))
        driver.find_element(By.ID, "start").click()
        wait_until(lambda: text() == "uploaded", 60, f"the upload ({text()})")
        assert driver.find_element(By.ID, "upload-progress").get_attribute("data-via") == "store"
        job_id = driver.find_element(By.ID, "job-id").text
        with s3_stack.stack.client() as client:
            job = wait_for_job(client, job_id, stack=s3_stack.stack, timeout=300)
        assert job["state"] == "succeeded" and job["upload_name"] == HEADSQ.path.name, job
        assert f"{PREFIX}/jobs/{job_id}/upload" in s3_stack.objects(job_id)
    finally:
        driver.quit()


def test_an_idempotency_key_begins_one_direct_upload(s3_stack: S3Stack) -> None:
    data = HEADSQ.path.read_bytes()
    body = {"filename": "headsq.zip", "size": len(data), "params": HEADSQ.params}
    key = {"Idempotency-Key": "direct-" + os.urandom(8).hex()}
    with s3_stack.stack.client() as client:
        first = client.post("/v1/uploads", json=body, headers=key)
        assert first.status_code == 201 and "idempotent-replayed" not in first.headers, first.text
        again = client.post("/v1/uploads", json=body, headers=key)  # the answer was lost: the same upload
        assert again.status_code == 201 and again.headers["idempotent-replayed"] == "true", again.text
        up = again.json()
        assert up["id"] == first.json()["id"] and again.headers["location"] == first.headers["location"]
        assert len(s3_stack.pending()) == 1  # one multipart upload in the store, not two
        other = client.post("/v1/uploads", json={**body, "filename": "other.zip"}, headers=key)
        assert assert_problem(other, 422)["code"] == "idempotency_key_reused"
        (part,) = up["parts"]  # the replayed links work
        put_part(part, data)
        done = client.post(up["complete_url"], json={})
        assert done.status_code == 202 and done.json()["id"] == up["id"], done.text
        assert_problem(client.post("/v1/uploads", json=body, headers=key), 404)  # completed: nothing to begin again
        assert client.delete(f"/v1/jobs/{up['id']}").status_code == 204
        assert not s3_stack.pending()
