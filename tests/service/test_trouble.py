"""The service under trouble, against real processes: hostile and broken uploads, bad parameters, keys and
visibility, signed links (forged, expired, Range and ETag), cancel and delete, progress, a worker killed with
SIGKILL mid-job, and Redis restarted with jobs queued."""

from __future__ import annotations

import io
import json
import time
import zipfile
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.service.checks import assert_problem, assert_succeeded, check_outputs
from tests.service.conftest import (
    HEADSQ,
    Scan,
    StackFactory,
    bomb_of_small_members,
    corrupt_member_zip,
    hostile_tar,
    many_members_zip,
    mixed_sizes_zip,
    no_images_zip,
    png_bytes,
    slice_zip,
    sphere_volume,
    traversal_zip,
    zip_bomb,
)
from tests.service.procs import (
    TERMINAL_STATES,
    ServiceStack,
    submit,
    wait_for_job,
    wait_until,
)

HEAVY_STAGES = ("gaussian", "isosurface", "islands", "decimate", "smooth", "normals")


def _job_files(stack: ServiceStack, job_id: str) -> list[Path]:
    """Every file the job left in the data folder (in any folder named after it)."""
    return sorted(p for d in stack.data_dir.rglob(job_id) if d.is_dir() for p in d.rglob("*") if p.is_file())


def _submit_ok(client: httpx.Client, scan: Scan, params: dict[str, Any] | None = None) -> str:
    resp = submit(client, scan.path, scan.params if params is None else params)
    assert resp.status_code == 202, resp.text
    return str(resp.json()["id"])


# -- uploads seen to be wrong at once -----------------------------------------------------------------------------
REFUSED_UPLOADS = {
    "empty": lambda: b"",
    "pdf": lambda: b"%PDF-1.4\n" + bytes(range(256)) * 40,
    "random": lambda: bytes((i * 7919 + 13) % 251 for i in range(20_000)),
    "truncated-zip": lambda: slice_zip(sphere_volume((8, 16, 16)))[:300],
    "no-images": no_images_zip,
    "zip-bomb": zip_bomb,
    "traversal-dotdot": lambda: traversal_zip("dotdot"),
    "traversal-absolute": lambda: traversal_zip("absolute"),
    "traversal-backslash": lambda: traversal_zip("backslash"),
    "tar-dotdot": lambda: hostile_tar("dotdot"),
    "too-many-members": many_members_zip,
    "bomb-of-small-members": bomb_of_small_members,  # each at the per-member ratio floor, 300 MB in all
}


@pytest.mark.parametrize("kind", list(REFUSED_UPLOADS))
def test_bad_archive_refused_at_upload(kind: str, stack: ServiceStack, client_a: httpx.Client) -> None:
    before = client_a.get("/v1/jobs", params={"limit": 1}).json()["total"]
    resp = submit(client_a, REFUSED_UPLOADS[kind](), HEADSQ.params, filename=f"{kind}.zip")
    body = assert_problem(resp, (415, 422))
    assert len(body["detail"]) > 10, body
    assert client_a.get("/v1/jobs", params={"limit": 1}).json()["total"] == before, "a refused upload made a job"
    assert not list(stack.data_dir.rglob("bonemesh_evil_*")) and not Path("/tmp/bonemesh_evil_0000.png").exists()


# -- uploads whose trouble shows only when loading: a failed job with a reason, never a stuck one ----------------
def holed_png_zip() -> bytes:
    """A numbered PNG stack with slice 5 of 12 left out."""
    whole = zipfile.ZipFile(io.BytesIO(slice_zip(sphere_volume((12, 32, 32)))))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for info in whole.infolist():
            if not info.filename.endswith("_0005.png"):
                zf.writestr(info, whole.read(info))
    return buf.getvalue()


def holed_dicom_zip() -> bytes:
    """A CT series of 10 images 1 mm apart with the sixth left out."""
    from tests.engine.dicom_factory import series

    files = series(lambda p: 1000.0 * (np.linalg.norm(p, axis=-1) < 4) - 1000.0, positions_mm=list(range(10)))
    del files["IM6"]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in files.items():
            zf.writestr(f"{name}.dcm", data)
    return buf.getvalue()


FAILING_JOBS = {
    # name: (archive, params, words of which the message must hold one)
    "mixed-sizes": (mixed_sizes_zip, {"iso": 500, "spacing": [1, 1, 1]}, ("size", "shape", "every slice")),
    "corrupt-png": (corrupt_member_zip, {"iso": 500, "spacing": [1, 1, 1]}, ("decode", "corrupt", "truncated", "read")),
    "no-spacing": (lambda: slice_zip(sphere_volume()), {"iso": 500}, ("spacing", "voxel size")),
    "no-surface": (lambda: HEADSQ.path.read_bytes(), {"iso": 60000, "spacing": [1.5, 3.2, 3.2]}, ("surface",)),
    "one-png": (
        lambda: png_bytes(sphere_volume((1, 32, 32))[0]),
        {"iso": 500, "spacing": [1, 1, 1]},
        ("slice", "dimension"),
    ),
    "missing-slice-png": (holed_png_zip, {"iso": 500, "spacing": [1, 1, 1]}, ("1 are missing: slices/slice_0005.png",)),
    "missing-slice-dicom": (holed_dicom_zip, {"preset": "bone"}, ("1 slice(s) missing between im5.dcm and im7.dcm",)),
}
FAILING_CODES = {"missing-slice-png": "incomplete_series", "missing-slice-dicom": "incomplete_series"}
SEEN_AT_UPLOAD_OK = ("mixed-sizes", "corrupt-png", "one-png", "no-spacing")


@pytest.mark.parametrize("kind", list(FAILING_JOBS))
def test_load_problem_fails_the_job_with_a_reason(kind: str, stack: ServiceStack, client_a: httpx.Client) -> None:
    make, params, words = FAILING_JOBS[kind]
    resp = submit(client_a, make(), params, filename=f"{kind}.zip")
    if resp.status_code != 202:  # seen already at upload: fine too, if it is a 4xx problem with a reason
        assert kind in SEEN_AT_UPLOAD_OK, f"{kind} cannot be seen at upload: {resp.text}"
        body = assert_problem(resp, (415, 422))
        assert any(w in body["detail"].lower() for w in words), body
        return
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=120)
    assert job["state"] == "failed", json.dumps(job)
    error = job["error"]
    assert error and error["code"] and error["code"] != "internal_error", error
    assert any(w in error["message"].lower() for w in words), error
    assert error["code"] == FAILING_CODES.get(kind, error["code"]), error
    assert job["outputs"] in (None, []), job
    assert job["finished_at"] is not None, job


def test_symlink_member_is_never_followed(stack: ServiceStack, client_a: httpx.Client) -> None:
    """A tar whose extra 'slice' is a symlink to /etc/passwd: refused at upload, or the link is skipped."""
    resp = submit(client_a, hostile_tar("symlink"), {"iso": 500, "spacing": [1, 1, 1]}, filename="link.tar.gz")
    if resp.status_code != 202:
        assert_problem(resp, (415, 422))
        return
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=120)
    assert job["state"] in ("succeeded", "failed"), job
    if job["state"] == "succeeded":
        report = httpx.get(next(o["url"] for o in job["outputs"] if o["name"] == "report.json")).json()
        assert report["input"]["shape_zyx"] == [8, 16, 16], report["input"]


# -- parameters and request shape ---------------------------------------------------------------------------------
BAD_PARAMS = {
    "reduction-above-1": ({"reduction": 1.5}, "reduction"),
    "reduction-zero": ({"reduction": 0}, "reduction"),
    "iso-not-number": ({"iso": "high"}, "iso"),
    "spacing-two": ({"spacing": [1.0, 1.0]}, "spacing"),
    "spacing-negative": ({"spacing": [1.0, -1.0, 1.0]}, "spacing"),
    "unknown-field": ({"colour": "ivory"}, "colour"),
    "unknown-preset": ({"preset": "cartilage"}, "preset"),
    "iterations-zero": ({"iterations": 0}, "iterations"),
    "angle-90": ({"angle": 90}, "angle"),
    "max-triangles-tiny": ({"max_triangles": 2}, "max_triangles"),
    "iso-and-preset": ({"iso": 300, "preset": "bone"}, ("iso", "preset")),
    "spacing-1e300": ({"spacing": [1e300, 3.2, 3.2]}, "spacing"),
    "spacing-1e-300": ({"spacing": [1e-300, 3.2, 3.2]}, "spacing"),
    "min-island-infinity": ({"min_island_mm3": float("inf")}, "min_island_mm3"),
    "iso-nan": ({"iso": float("nan")}, "iso"),
}


@pytest.mark.parametrize("kind", list(BAD_PARAMS))
def test_invalid_params_name_the_field(kind: str, client_a: httpx.Client) -> None:
    params, field = BAD_PARAMS[kind]
    resp = submit(client_a, HEADSQ.path, params)
    body = assert_problem(resp, 422)
    assert isinstance(body.get("errors"), list) and body["errors"], body
    fields = (field,) if isinstance(field, str) else field
    assert any(f in json.dumps(body["errors"]) for f in fields), f"errors do not name {fields}: {body}"


@pytest.mark.parametrize("text", ["{", "[1, 2, 3]", '"iso"', "null"])
def test_params_not_a_json_object(text: str, client_a: httpx.Client) -> None:
    resp = client_a.post(
        "/v1/jobs",
        files={"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")},
        data={"params": text},
    )
    assert_problem(resp, 422)


def test_request_shape_errors(client_a: httpx.Client) -> None:
    assert_problem(client_a.post("/v1/jobs", json={"iso": 300}), (415, 422))
    assert_problem(client_a.post("/v1/jobs", data={"params": "{}"}, files={"other": ("x", b"1")}), (400, 422))


def test_too_large_upload_is_413(stack: ServiceStack, client_a: httpx.Client) -> None:
    limit = int(stack.env["BONEMESH_MAX_UPLOAD_BYTES"])
    resp = submit(client_a, b"\0" * (limit + (2 << 20)), HEADSQ.params, filename="huge.zip")
    assert_problem(resp, 413)

    def chunks() -> Any:  # no Content-Length: the limit must hold on the streamed bytes too
        boundary = "b0nemesh"
        yield f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="x.zip"\r\n\r\n'.encode()
        for _ in range(limit // (1 << 20) + 3):
            yield b"\0" * (1 << 20)
        yield f"\r\n--{boundary}--\r\n".encode()

    resp = client_a.post(
        "/v1/jobs", content=chunks(), headers={"Content-Type": "multipart/form-data; boundary=b0nemesh"}
    )
    assert_problem(resp, 413)
    assert not [p for p in stack.data_dir.rglob("*") if p.is_file() and p.stat().st_size > limit], "upload kept"


# -- keys and visibility ------------------------------------------------------------------------------------------
def test_missing_or_wrong_key_is_401(anon: httpx.Client, headsq_job: dict[str, Any]) -> None:
    job_url = f"/v1/jobs/{headsq_job['id']}"
    for headers in (
        {},
        {"X-API-Key": "not-a-key"},
        {"X-API-Key": "key-a\tkey-b"},
        {"X-API-Key": "KEY-A"},
        {"X-API-Key": ""},
    ):
        assert_problem(anon.get("/v1/jobs", headers=headers), 401)
        assert_problem(anon.get(job_url, headers=headers), 401)
        assert_problem(anon.delete(job_url, headers=headers), 401)
        resp = anon.post("/v1/jobs", headers=headers, files={"file": ("h.zip", b"PK\x05\x06" + bytes(18))})
        assert_problem(resp, 401)


def test_jobs_are_visible_only_to_their_key(
    client_a: httpx.Client, client_b: httpx.Client, headsq_job: dict[str, Any]
) -> None:
    job_id = headsq_job["id"]
    assert_problem(client_b.get(f"/v1/jobs/{job_id}"), 404)
    assert_problem(client_b.delete(f"/v1/jobs/{job_id}"), 404)
    listing = client_b.get("/v1/jobs", params={"limit": 200}).json()
    assert job_id not in [j["id"] for j in listing["items"]]
    assert client_a.get(f"/v1/jobs/{job_id}").json()["state"] == "succeeded"  # b's DELETE did nothing
    assert_problem(client_a.get("/v1/jobs/0123456789abcdef0123456789abcdef"), 404)
    assert_problem(client_a.get("/v1/jobs/..%2F..%2Fetc"), 404)


def test_list_is_newest_first_and_paginated(client_a: httpx.Client) -> None:
    ids = [_submit_ok(client_a, HEADSQ, {**HEADSQ.params, "iso": 60000 + i}) for i in range(3)]
    for job_id in ids:  # cancel at once: the records stay, the worker is spared (409: it already failed, no surface)
        assert client_a.post(f"/v1/jobs/{job_id}/cancel").status_code in (200, 409)
    first = client_a.get("/v1/jobs", params={"limit": 3, "offset": 0}).json()
    assert [j["id"] for j in first["items"]] == ids[::-1], first
    assert first["limit"] == 3 and first["offset"] == 0 and first["total"] >= 3
    page = client_a.get("/v1/jobs", params={"limit": 2, "offset": 1}).json()
    assert [j["id"] for j in page["items"]] == [ids[1], ids[0]], page
    assert_problem(client_a.get("/v1/jobs", params={"limit": -1}), 422)


# -- signed links -------------------------------------------------------------------------------------------------
def _token(url: str) -> str:
    return url.rsplit("/v1/files/", 1)[1]


def test_forged_links_are_403(anon: httpx.Client, headsq_job: dict[str, Any], client_a: httpx.Client) -> None:
    job = client_a.get(f"/v1/jobs/{headsq_job['id']}").json()
    urls = {o["name"]: o["url"] for o in job["outputs"]}
    token = _token(urls["model.stl"])
    flip = "A" if token[-1] != "A" else "B"
    other = _token(urls["phone.glb"])
    forged = [
        token[:-1] + flip,  # signature changed
        flip + token[1:],  # payload changed
        token + "A",
        token.split(".")[0],  # no signature
        other.split(".")[0] + "." + token.split(".")[-1],  # one file's payload, another's signature
        "not-a-token",
        "a.b.c",
    ]
    for bad in forged:
        assert_problem(anon.get(f"/v1/files/{bad}"), 403)
    assert anon.get(urls["model.stl"]).status_code == 200  # the genuine link still works


def test_links_expire(stack: ServiceStack, headsq_job: dict[str, Any]) -> None:
    """A second API process on the same database with a 2 s link lifetime (and no reconciler of its own)."""
    url = stack.start_server(extra_env={"BONEMESH_URL_TTL_SECONDS": "2", "BONEMESH_RECONCILE_SECONDS": "3600"})
    try:
        with stack.client("key-a", base_url=url) as client, stack.client(None, base_url=url) as anon:
            job = client.get(f"/v1/jobs/{headsq_job['id']}").json()
            link = next(o["url"] for o in job["outputs"] if o["name"] == "report.json")
            assert link.startswith(f"{url}/v1/files/")
            assert anon.get(link).status_code == 200
            time.sleep(3.1)  # past the lifetime (the wait, not an assertion)
            body = assert_problem(anon.get(link), 403)
            assert "expire" in body["detail"].lower(), body
            # the same secret: the long-lived link of the main server works on this one too
            job_main = httpx.get(f"{stack.base_url}/v1/jobs/{headsq_job['id']}", headers={"X-API-Key": "key-a"})
            main_link = next(o["url"] for o in job_main.json()["outputs"] if o["name"] == "report.json")
            assert anon.get(f"{url}/v1/files/{_token(main_link)}").status_code == 200
    finally:
        proc = stack.servers.pop()
        proc.stop()


def test_download_range_and_etag(anon: httpx.Client, client_a: httpx.Client, headsq_job: dict[str, Any]) -> None:
    job = client_a.get(f"/v1/jobs/{headsq_job['id']}").json()
    link = next(o["url"] for o in job["outputs"] if o["name"] == "model.stl")
    full = anon.get(link)
    assert full.status_code == 200
    data, etag, size = full.content, full.headers["etag"], len(full.content)
    assert full.headers.get("accept-ranges") == "bytes", full.headers
    assert 'filename="model.stl"' in full.headers["content-disposition"], full.headers
    assert anon.get(link).headers["etag"] == etag

    part = anon.get(link, headers={"Range": "bytes=0-99"})
    assert part.status_code == 206 and part.content == data[:100], part.headers
    assert part.headers["content-range"] == f"bytes 0-99/{size}"
    tail = anon.get(link, headers={"Range": "bytes=-84"})
    assert tail.status_code == 206 and tail.content == data[-84:]
    mid = anon.get(link, headers={"Range": f"bytes=84-{size - 1}"})
    assert mid.status_code == 206 and mid.content == data[84:]
    assert anon.get(link, headers={"Range": f"bytes={size + 10}-"}).status_code == 416

    assert anon.get(link, headers={"Range": "bytes=0-9", "If-Range": etag}).status_code == 206
    stale = anon.get(link, headers={"Range": "bytes=0-9", "If-Range": '"stale-etag"'})
    assert stale.status_code == 200 and stale.content == data  # changed since: the whole file
    cached = anon.get(link, headers={"If-None-Match": etag})
    assert cached.status_code in (200, 304)
    if cached.status_code == 200:
        assert cached.content == data


# -- cancel and delete --------------------------------------------------------------------------------------------
def test_cancel_running_and_queued_then_delete_finished(
    stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client, long_scan: Scan
) -> None:
    running = _submit_ok(client_a, long_scan)
    wait_for_job(client_a, running, stack=stack, timeout=180, until=lambda j: j["state"] == "running")
    queued = _submit_ok(client_a, HEADSQ)  # the one worker is busy: this one waits
    assert client_a.get(f"/v1/jobs/{queued}").json()["state"] == "queued"

    assert client_a.post(f"/v1/jobs/{queued}/cancel").json()["state"] == "cancelled"
    assert client_a.post(f"/v1/jobs/{running}/cancel").json()["state"] == "cancelled"
    for job_id in (queued, running):
        assert client_a.get(f"/v1/jobs/{job_id}").json()["state"] == "cancelled"
        assert client_a.post(f"/v1/jobs/{job_id}/cancel").status_code == 200  # again: harmless

    # the worker gives the running job up and takes the next; the cancelled queued one never runs
    sentinel = _submit_ok(client_a, HEADSQ)
    done = wait_for_job(client_a, sentinel, stack=stack, timeout=300)
    outputs = assert_succeeded(done, stack.base_url)
    for job_id in (queued, running):
        job = client_a.get(f"/v1/jobs/{job_id}").json()
        assert job["state"] == "cancelled" and job["outputs"] in (None, []), job
        assert job_id == running or job["started_at"] is None, job
        wait_until(lambda job_id=job_id: not _job_files(stack, job_id), 30, f"files of cancelled job {job_id} gone")

    # a finished job cannot be cancelled; deleting it removes it and its files: its links stop working
    assert_problem(client_a.post(f"/v1/jobs/{sentinel}/cancel"), 409)
    link = outputs["model.stl"]["url"]
    assert anon.get(link).status_code == 200
    assert client_a.delete(f"/v1/jobs/{sentinel}").status_code == 204
    assert_problem(anon.get(link), 404)
    assert_problem(client_a.get(f"/v1/jobs/{sentinel}"), 404)  # deleted: gone, as HTTP clients expect
    assert_problem(client_a.delete(f"/v1/jobs/{sentinel}"), 404)
    assert not _job_files(stack, sentinel)
    for job_id in (queued, running):  # delete a cancelled one too
        assert client_a.delete(f"/v1/jobs/{job_id}").status_code == 204
        assert_problem(client_a.get(f"/v1/jobs/{job_id}"), 404)


# -- progress -----------------------------------------------------------------------------------------------------
def test_progress_moves_through_the_stages(stack: ServiceStack, client_a: httpx.Client, long_scan: Scan) -> None:
    seen: list[tuple[str, str | None, float]] = []
    job_id = _submit_ok(client_a, long_scan)
    job = wait_for_job(
        client_a,
        job_id,
        stack=stack,
        timeout=300,
        interval=0.05,
        on_poll=lambda j: seen.append((j["state"], j["stage"], j["progress"])),
    )
    assert job["state"] == "succeeded", job
    progress = [p for _, _, p in seen]
    assert all(0 <= p <= 100 for p in progress), seen
    assert progress == sorted(progress), f"progress went back: {seen}"
    running_stages = list(dict.fromkeys(stage for state, stage, _ in seen if state == "running"))
    assert len(running_stages) >= 3, f"saw only {running_stages} while running: {seen}"
    assert set(running_stages) & set(HEAVY_STAGES), running_stages
    assert len({p for state, _, p in seen if state == "running"}) >= 3, seen
    assert seen[-1][2] == 100


# -- a worker killed mid-job --------------------------------------------------------------------------------------
def test_worker_killed_mid_job_completes_once(make_stack: StackFactory, long_scan: Scan) -> None:
    _, stack = make_stack(workers=1)
    anon = stack.client(None)
    with stack.client("key-a") as client, anon:
        job_id = _submit_ok(client, long_scan)
        job = wait_for_job(
            client,
            job_id,
            stack=stack,
            timeout=180,
            interval=0.1,
            until=lambda j: j["state"] == "running" and j["stage"] in HEAVY_STAGES,
        )
        assert job["attempts"] == 1, job
        stack.workers[0].kill()  # SIGKILL to the worker's whole process group, mid-pipeline
        killed_at = client.get(f"/v1/jobs/{job_id}").json()
        assert killed_at["state"] in ("running", "queued"), killed_at  # not failed: the worker died, not the job

        stack.start_worker()
        job = wait_for_job(client, job_id, stack=stack, timeout=300)
        outputs = assert_succeeded(job, stack.base_url)
        assert job["attempts"] == 2, job
        check_outputs(anon, outputs, long_scan.shape_zyx, long_scan.spacing_zyx_mm)

        files = _job_files(stack, job_id)
        names = [p.name for p in files if not any(part.startswith(".") for part in p.parts)]
        for name in ("model.stl", "model.glb", "phone.glb", "ar.glb", "report.json"):
            assert names.count(name) == 1, f"{name} {names.count(name)} times: {files}"


def test_job_that_keeps_killing_workers_fails(make_stack: StackFactory, long_scan: Scan) -> None:
    """With BONEMESH_MAX_ATTEMPTS=1, a job whose worker died once is failed, not retried forever."""
    _, stack = make_stack(workers=1, extra_env={"BONEMESH_MAX_ATTEMPTS": "1"})
    with stack.client("key-a") as client:
        job_id = _submit_ok(client, long_scan)
        wait_for_job(
            client,
            job_id,
            stack=stack,
            timeout=180,
            interval=0.1,
            until=lambda j: j["state"] == "running" and j["stage"] in HEAVY_STAGES,
        )
        stack.workers[0].kill()
        stack.start_worker()
        job = wait_for_job(client, job_id, stack=stack, timeout=120)
        assert job["state"] == "failed", job
        assert job["error"] and job["error"]["code"] and job["error"]["message"], job
        assert job["outputs"] in (None, []), job
        follow = _submit_ok(client, HEADSQ)  # the worker is fine afterwards
        assert wait_for_job(client, follow, stack=stack, timeout=300)["state"] == "succeeded"


# -- Redis restarted with jobs queued -----------------------------------------------------------------------------
def test_redis_restart_loses_no_job(make_stack: StackFactory) -> None:
    redis, stack = make_stack(workers=0)  # no worker yet: the jobs wait in Redis
    with stack.client("key-a") as client, stack.client(None) as anon:
        ids = [_submit_ok(client, HEADSQ) for _ in range(2)]
        assert {client.get(f"/v1/jobs/{i}").json()["state"] for i in ids} == {"queued"}

        redis.stop()  # no persistence: the queued messages are gone
        ready = anon.get("/readyz")
        assert ready.status_code == 503 and "redis" in ready.text.lower(), ready.text
        during = submit(client, HEADSQ.path, HEADSQ.params)  # accepted (and sent later) or refused, never a 500
        if during.status_code == 202:
            ids.append(during.json()["id"])
        else:
            assert_problem(during, 503)
        redis.start()
        wait_until(lambda: anon.get("/readyz").status_code == 200, 60, "/readyz to recover after Redis came back")

        stack.start_worker()
        for job_id in ids:
            job = wait_for_job(client, job_id, stack=stack, timeout=300)
            assert job["state"] == "succeeded", job
            assert job["attempts"] == 1, job
        assert all(j["state"] in TERMINAL_STATES for j in client.get("/v1/jobs").json()["items"])
