"""The API's contract as clients and generated SDKs meet it: polling a job with ETag / If-None-Match (304) and
Retry-After, its declared Cache-Control; the API-key security scheme, readable operation ids and declared response
headers in the OpenAPI document; problem types with stable URIs, one per code, documented; the ``webhooks`` entry of
the job-finished callback."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from core.db import Database, utcnow
from core.settings import Settings
from service.headers import job_etag
from service.problems import CODES
from tests.service.conftest import HEADSQ, StackFactory

KEY = {"X-API-Key": "key-a"}
REPO = Path(__file__).resolve().parents[2]


def _app(tmp_path: Path, **settings: Any) -> TestClient:
    from service.app import create_app

    base = {"data_dir": tmp_path, "api_keys": ["key-a", "key-b"], "secret_key": "s" * 32}
    base |= {"redis_url": "redis://127.0.0.1:1/0", "reconcile_seconds": 3600}
    return TestClient(create_app(Settings(**{**base, **settings})))


def _submit(client: Any) -> dict[str, Any]:
    files = {"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")}
    resp = client.post("/v1/jobs", headers=KEY, files=files, data={"params": json.dumps(HEADSQ.params)})
    assert resp.status_code == 202, resp.text
    return resp.json()  # type: ignore[no-any-return]


# -- polling: ETag, 304, Retry-After, Cache-Control -------------------------------------------------------------
def test_polling_a_job_with_etag_and_retry_after(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        job = _submit(client)
        url = f"/v1/jobs/{job['id']}"
        first = client.get(url, headers=KEY)
        assert first.status_code == 200
        etag = first.headers["etag"]
        assert re.fullmatch(r'W/"[0-9a-f]{32}"', etag), etag
        assert first.headers["cache-control"] == "private, no-cache"
        assert first.headers["retry-after"] == "5"  # queued
        same = client.get(url, headers={**KEY, "If-None-Match": etag})
        assert same.status_code == 304 and same.content == b""
        assert same.headers["etag"] == etag and same.headers["retry-after"] == "5"
        assert (
            client.get(url, headers={**KEY, "If-None-Match": f'"other", {etag.removeprefix("W/")}'}).status_code == 304
        )
        assert client.get(url, headers={**KEY, "If-None-Match": '"other"'}).status_code == 200
        assert client.get(url, headers={"X-API-Key": "key-b", "If-None-Match": etag}).status_code == 404

        db: Database = client.app.state.services.db  # type: ignore[attr-defined]
        assert db.claim(job["id"], "host:1:w", utcnow())
        running = client.get(url, headers={**KEY, "If-None-Match": etag})
        assert running.status_code == 200 and running.json()["state"] == "running"
        assert running.headers["etag"] != etag and running.headers["retry-after"] == "2"
        assert db.beat(job["id"], "host:1:w", stage="marching", progress=40.0)
        moved = client.get(url, headers={**KEY, "If-None-Match": running.headers["etag"]})
        assert moved.status_code == 200 and moved.json()["progress"] == 40.0  # progress is part of the state

        output = {"name": "model.stl", "kind": "stl", "media_type": "model/stl", "bytes": 10, "triangles": 2}
        assert db.finish(job["id"], "host:1:w", "succeeded", outputs=[output], progress=100.0)
        done = client.get(url, headers=KEY)
        assert done.status_code == 200 and "retry-after" not in done.headers
        again = client.get(url, headers={**KEY, "If-None-Match": done.headers["etag"]})
        assert again.status_code == 304 and "retry-after" not in again.headers  # fresh links alone change nothing
        body = done.json()
        later = job_etag(body, 3600, now=1e9 + 1800)  # half the links' lifetime on: a new ETag, so new links
        assert job_etag(body, 3600, now=1e9) != later and job_etag(body, 3600, now=1e9 + 10) == job_etag(
            body, 3600, 1e9
        )


def test_polling_a_real_server(make_stack: StackFactory) -> None:
    _, stack = make_stack(workers=0)
    with stack.client("key-a") as client:
        files = {"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")}
        made = client.post("/v1/jobs", files=files, data={"params": json.dumps(HEADSQ.params)})
        assert made.status_code == 202, made.text
        url = made.headers["location"]
        seen = client.get(url)
        assert seen.status_code == 200 and seen.headers["retry-after"] == "5"
        cached = client.get(url, headers={"If-None-Match": seen.headers["etag"]})
        assert cached.status_code == 304 and cached.headers["cache-control"] == "private, no-cache"


def test_cors_exposes_the_polling_and_idempotency_headers(tmp_path: Path) -> None:
    origin = "https://app.example.org"
    with _app(tmp_path, cors_origins=[origin]) as client:
        pre = client.options(
            "/v1/jobs",
            headers={"Origin": origin, "Access-Control-Request-Method": "POST",
                     "Access-Control-Request-Headers": "x-api-key, idempotency-key"},
        )  # fmt: skip
        assert pre.status_code == 200 and "idempotency-key" in pre.headers["access-control-allow-headers"].lower()
        got = client.get("/v1/jobs", headers={**KEY, "Origin": origin})
        exposed = got.headers["access-control-expose-headers"].lower()
        assert "retry-after" in exposed and "idempotent-replayed" in exposed and "etag" in exposed


# -- problem types ------------------------------------------------------------------------------------------------
def test_every_problem_code_has_its_type_and_is_documented(tmp_path: Path) -> None:
    doc = (REPO / "docs" / "api.md").read_text()
    for code, (status, _) in CODES.items():
        assert f"| `{code}` | `urn:bonemesh:problem:{code}` | {status} |" in doc, code
    with _app(tmp_path) as client:
        answers = {
            "unauthorized": client.get("/v1/jobs"),
            "not_found": client.get("/v1/jobs/nope", headers=KEY),
            "method_not_allowed": client.put("/v1/jobs", headers=KEY),
            "invalid_request": client.get("/v1/jobs?limit=0", headers=KEY),
            "link_invalid": client.get("/v1/files/forged"),
            "unsupported_media_type": client.post("/v1/jobs", headers=KEY, content=b"x"),
        }
        files = {"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")}
        data = {"params": json.dumps(HEADSQ.params), "callback_url": "http://127.0.0.1:9/hook"}
        answers["callback_refused"] = client.post("/v1/jobs", headers=KEY, files=files, data=data)
        for code, resp in answers.items():
            body = resp.json()
            assert resp.headers["content-type"] == "application/problem+json", (code, resp.text)
            assert (body["code"], body["type"]) == (code, f"urn:bonemesh:problem:{code}"), (code, body)
            assert body["status"] == CODES[code][0] == resp.status_code


@pytest.mark.parametrize("status", [400, 401, 404, 409, 413, 415, 422, 500, 503, 507])
def test_status_defaults_are_codes(status: int) -> None:
    from service.problems import code_of

    assert CODES[code_of(status)][0] == status


# -- the OpenAPI document: security scheme, operation ids, declared headers -----------------------------------------
def _doc() -> dict[str, Any]:
    from service.openapi import DEFAULT

    return json.loads(DEFAULT.read_text())  # type: ignore[no-any-return]


def _ops(doc: dict[str, Any]) -> dict[str, tuple[str, str, dict[str, Any]]]:
    return {op["operationId"]: (path, method, op) for path, ops in doc["paths"].items() for method, op in ops.items()}


def test_the_api_key_is_a_security_scheme() -> None:
    doc = _doc()
    assert doc["components"]["securitySchemes"]["ApiKey"] == {
        "type": "apiKey",
        "in": "header",
        "name": "X-API-Key",
        "description": doc["components"]["securitySchemes"]["ApiKey"]["description"],
    }
    for op_id, (path, _, op) in _ops(doc).items():
        names = {p["name"].lower() for p in op.get("parameters", [])}
        assert "x-api-key" not in names, op_id  # never a plain header parameter
        public = path in ("/healthz", "/readyz") or path.startswith("/v1/files/")
        assert op["security"] == ([] if public else [{"ApiKey": []}]), (op_id, op["security"])


def test_operation_ids_are_readable() -> None:
    ops = _ops(_doc())
    for op_id in ops:
        assert re.fullmatch(r"[a-z]+(?:[A-Z][a-z]+)*", op_id), op_id
    expected = {
        "createJob": ("/v1/jobs", "post"),
        "listJobs": ("/v1/jobs", "get"),
        "getJob": ("/v1/jobs/{job_id}", "get"),
        "cancelJob": ("/v1/jobs/{job_id}/cancel", "post"),
        "deleteJob": ("/v1/jobs/{job_id}", "delete"),
        "createUpload": ("/v1/uploads", "post"),
        "completeUpload": ("/v1/uploads/{upload_id}/complete", "post"),
        "downloadFile": ("/v1/files/{token}", "get"),
        "getWebhookSecret": ("/v1/webhook-secret", "get"),
    }
    for op_id, where in expected.items():
        assert ops[op_id][:2] == where, op_id


def test_response_headers_are_declared() -> None:
    ops = _ops(_doc())

    def headers(op_id: str, status: str) -> set[str]:
        return set(ops[op_id][2]["responses"][status].get("headers", {}))

    assert headers("createJob", "202") >= {"Location", "Idempotent-Replayed"}
    assert headers("createJob", "409") >= {"Retry-After"}
    assert headers("createUpload", "201") >= {"Location", "Idempotent-Replayed"}
    assert headers("completeUpload", "202") >= {"Location"}
    assert headers("getJob", "200") >= {"ETag", "Cache-Control", "Retry-After"}
    assert headers("getJob", "304") >= {"ETag", "Cache-Control", "Retry-After"}
    assert headers("downloadFile", "200") >= {"ETag", "Cache-Control"}
    assert headers("listJobs", "503") >= {"Retry-After"}
    for op_id in ("createJob", "createUpload"):
        assert "Idempotency-Key" in {p["name"] for p in ops[op_id][2]["parameters"]}


def test_swagger_has_the_authorize_button(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        spec = client.get("/openapi.json").json()
        assert "ApiKey" in spec["components"]["securitySchemes"]
        assert client.get("/v1/jobs").status_code == 401  # no key: 401 as before
        assert client.get("/v1/jobs", headers={"X-API-Key": "wrong"}).status_code == 401
        assert client.get("/v1/jobs", headers=KEY).status_code == 200


# -- the webhooks entry -----------------------------------------------------------------------------------------------
def test_the_job_finished_webhook_is_described_as_sent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from service import webhooks
    from service.schemas import JobOut

    doc = _doc()
    assert doc["openapi"].startswith("3.1")
    hook = doc["webhooks"]["job-finished"]["post"]
    assert hook["operationId"] == "jobFinished"
    assert hook["requestBody"]["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/JobOut"}
    declared = {p["name"] for p in hook["parameters"] if p["in"] == "header"}
    assert declared == {"webhook-id", "webhook-timestamp", "webhook-signature"}
    assert set(hook["responses"]) == {"2XX", "default"}

    sent: list[tuple[str, bytes, dict[str, str]]] = []

    def post(url: str, body: bytes, headers: dict[str, str], timeout: float, *pinned: Any) -> int:
        sent.append((url, body, headers))
        return 204

    monkeypatch.setattr(webhooks, "post", post)
    with _app(tmp_path, webhook_allow_private=True) as client:
        files = {"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")}
        data = {"params": json.dumps(HEADSQ.params), "callback_url": "http://127.0.0.1:9/hook"}
        job = client.post("/v1/jobs", headers=KEY, files=files, data=data).json()
        assert client.post(f"/v1/jobs/{job['id']}/cancel", headers=KEY).status_code == 200
        svc = client.app.state.services  # type: ignore[attr-defined]
        assert webhooks.deliver(svc, svc.db.get(job["id"])) == "delivered"
    ((url, body, headers),) = sent
    assert url == "http://127.0.0.1:9/hook" and declared <= set(headers)
    assert JobOut.model_validate_json(body).state == "cancelled"
