"""What browser, phone and REST clients expect: webhooks (signed as Standard Webhooks, retried, refused for
private addresses), CORS, HEAD / If-None-Match / Cache-Control on downloads, and the page without its npm assets."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from core.settings import Settings
from service.webhooks import CallbackRefused, check_callback_url, next_delay, sign
from tests.service.checks import assert_succeeded
from tests.service.conftest import HEADSQ
from tests.service.procs import ServiceStack, submit, wait_for_job, wait_until

KEY = {"X-API-Key": "key-a"}


def _app(tmp_path: Path, **settings: Any) -> TestClient:
    from service.app import create_app

    base = {"data_dir": tmp_path, "api_keys": ["key-a"], "secret_key": "s" * 32, "redis_url": "redis://127.0.0.1:1/0"}
    return TestClient(create_app(Settings(**{**base, "reconcile_seconds": 3600, **settings})))


# -- webhooks: units ----------------------------------------------------------------------------------------------
def test_signature_is_standard_webhooks_hmac() -> None:
    secret = "whsec_" + base64.b64encode(b"0123456789abcdef0123456789abcdef").decode()
    body = b'{"id":"x"}'
    mac = hmac.new(b"0123456789abcdef0123456789abcdef", b"msg_1.1700000000." + body, hashlib.sha256).digest()
    assert sign(secret, "msg_1", 1700000000, body) == "v1," + base64.b64encode(mac).decode()


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:9/hook",
        "http://localhost/hook",
        "http://[::1]/hook",
        "http://169.254.169.254/latest/meta-data",
        "http://10.1.2.3/",
        "http://192.168.0.1/",
        "http://172.16.0.1/",
        "http://0.0.0.0/",
        "ftp://example.org/",
        "http://user:pw@example.org/",
    ],
)
def test_private_and_odd_callbacks_are_refused(url: str) -> None:
    with pytest.raises(CallbackRefused):
        check_callback_url(url, allow_private=False)


def test_loopback_allowed_only_by_the_setting() -> None:
    assert check_callback_url("http://127.0.0.1:9/hook", allow_private=True) == "http://127.0.0.1:9/hook"


def test_backoff_doubles() -> None:
    assert [next_delay(n, 2.0) for n in (1, 2, 3, 4)] == [2.0, 4.0, 8.0, 16.0]
    assert next_delay(60, 2.0) == 3600.0


def test_job_with_private_callback_is_refused_and_nothing_kept(tmp_path: Path) -> None:
    with _app(tmp_path) as client:
        files = {"file": ("headsq.zip", HEADSQ.path.read_bytes(), "application/zip")}
        data = {"params": json.dumps(HEADSQ.params), "callback_url": "http://127.0.0.1:8080/hook"}
        resp = client.post("/v1/jobs", headers=KEY, files=files, data=data)
        assert resp.status_code == 422, resp.text
        assert resp.json()["errors"][0]["field"] == "callback_url"
        assert client.get("/v1/jobs", headers=KEY).json()["total"] == 0
        assert not any((tmp_path / "jobs").iterdir())


# -- CORS ---------------------------------------------------------------------------------------------------------
def test_cors_preflight_for_configured_origins_only(tmp_path: Path) -> None:
    origin = "https://app.example.org"
    with _app(tmp_path, cors_origins=[origin]) as client:
        pre = client.options(
            "/v1/jobs",
            headers={"Origin": origin, "Access-Control-Request-Method": "POST",
                     "Access-Control-Request-Headers": "x-api-key"},
        )  # fmt: skip
        assert pre.status_code == 200, pre.text
        assert pre.headers["access-control-allow-origin"] == origin
        assert "x-api-key" in pre.headers["access-control-allow-headers"].lower()
        assert pre.headers.get("access-control-allow-credentials") != "true"
        got = client.get("/v1/jobs", headers={**KEY, "Origin": origin})
        assert got.headers["access-control-allow-origin"] == origin
        assert "etag" in got.headers["access-control-expose-headers"].lower()
        other = client.get("/v1/jobs", headers={**KEY, "Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers
    with _app(tmp_path / "none") as client:  # not configured: no CORS at all
        assert "access-control-allow-origin" not in client.get("/healthz", headers={"Origin": origin}).headers


# -- the page without node_modules --------------------------------------------------------------------------------
def test_page_serves_and_says_when_viewer_assets_are_missing(tmp_path: Path) -> None:
    with _app(tmp_path, assets_dir=tmp_path / "no-node-modules") as client:
        page = client.get("/")
        assert page.status_code == 200 and "text/html" in page.headers["content-type"]
        assert 'id="assets-missing"' in page.text
        assert client.get("/vendor/model-viewer.min.js").status_code == 404
        assert client.get("/static/page.js").status_code == 200
    with _app(tmp_path / "b") as client:  # the checkout's node_modules (the setup script installs them)
        assert 'id="assets-missing"' not in client.get("/").text
        js = client.get("/vendor/model-viewer.min.js")
        assert js.status_code == 200 and "javascript" in js.headers["content-type"]
        assert client.get("/vendor/draco/draco_decoder.wasm").headers["content-type"] == "application/wasm"
        assert client.get("/vendor/../package.json").status_code == 404


# -- downloads: HEAD, ETag, Cache-Control -------------------------------------------------------------------------
def test_head_etag_and_cache_control(headsq_job: dict[str, Any], anon: httpx.Client) -> None:
    out = next(o for o in headsq_job["outputs"] if o["name"] == "phone.glb")
    head = anon.head(out["url"])
    assert head.status_code == 200 and head.content == b""
    assert int(head.headers["content-length"]) == out["bytes"]
    etag = head.headers["etag"]
    max_age = int(head.headers["cache-control"].split("max-age=")[1])
    left = out["expires_at"]
    import datetime as dt

    remaining = (dt.datetime.fromisoformat(left) - dt.datetime.now(dt.UTC)).total_seconds()
    assert "private" in head.headers["cache-control"] and abs(max_age - remaining) < 120, (max_age, remaining)
    cached = anon.get(out["url"], headers={"If-None-Match": etag})
    assert cached.status_code == 304 and cached.content == b"" and cached.headers["etag"] == etag
    assert anon.get(out["url"], headers={"If-None-Match": '"other"'}).status_code == 200
    assert anon.head(out["url"] + "x").status_code == 403


# -- webhooks: live, with a receiver on loopback ------------------------------------------------------------------
class Receiver:
    """An HTTP server on 127.0.0.1 that records POSTs; the first ``fail_first`` answers are 500."""

    def __init__(self, fail_first: int = 0) -> None:
        self.calls: list[tuple[dict[str, str], bytes]] = []
        self.fail_first = fail_first
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers["content-length"]))
                receiver.calls.append(({k.lower(): v for k, v in self.headers.items()}, body))
                self.send_response(500 if len(receiver.calls) <= receiver.fail_first else 204)
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hooks/bonemesh"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    r = Receiver(fail_first=1)
    yield r
    r.close()


def _verify(secret: str, headers: dict[str, str], body: bytes) -> None:
    """The receiver's side of Standard Webhooks: recompute the HMAC, check the timestamp is recent."""
    key = base64.b64decode(secret.removeprefix("whsec_"))
    signed = f"{headers['webhook-id']}.{headers['webhook-timestamp']}.".encode() + body
    expected = base64.b64encode(hmac.new(key, signed, hashlib.sha256).digest()).decode()
    sigs = [s.split(",", 1)[1] for s in headers["webhook-signature"].split() if s.startswith("v1,")]
    assert any(hmac.compare_digest(expected, s) for s in sigs), headers
    assert abs(time.time() - int(headers["webhook-timestamp"])) < 300


def test_webhook_signed_retried_and_recorded(stack: ServiceStack, client_a: httpx.Client, receiver: Receiver) -> None:
    secret = client_a.get("/v1/webhook-secret").json()["secret"]
    assert secret.startswith("whsec_")
    resp = submit(client_a, HEADSQ.path, HEADSQ.params, extra={"callback_url": receiver.url})
    assert resp.status_code == 202, resp.text
    job_id = resp.json()["id"]
    assert resp.json()["webhook"] == {"url": receiver.url, "state": "pending", "attempts": []}
    assert_succeeded(wait_for_job(client_a, job_id, stack=stack, timeout=300), stack.base_url)
    job = wait_until(
        lambda: (j := client_a.get(f"/v1/jobs/{job_id}").json())["webhook"]["state"] == "delivered" and j,
        30,
        "the webhook to be delivered",
    )
    attempts = job["webhook"]["attempts"]
    assert [a["status"] for a in attempts] == [500, 204], attempts  # the 500 was retried
    assert len(receiver.calls) == 2
    ids = {h["webhook-id"] for h, _ in receiver.calls}
    assert len(ids) == 1, ids  # the same message id on the retry: receivers can drop duplicates
    for headers, body in receiver.calls:
        _verify(secret, headers, body)
        sent = json.loads(body)
        assert sent["id"] == job_id and sent["state"] == "succeeded"
        assert {o["name"] for o in sent["outputs"]} >= {"model.stl", "phone.glb"}
    other = httpx.get(f"{stack.base_url}/v1/webhook-secret", headers={"X-API-Key": "key-b"}).json()["secret"]
    assert other != secret  # a secret per key


def test_webhook_on_cancel(stack: ServiceStack, client_a: httpx.Client) -> None:
    r = Receiver()
    try:
        resp = submit(client_a, HEADSQ.path, HEADSQ.params, extra={"callback_url": r.url})
        job_id = resp.json()["id"]
        assert client_a.post(f"/v1/jobs/{job_id}/cancel").json()["state"] == "cancelled"
        wait_until(lambda: r.calls, 30, "the cancel webhook")
        assert json.loads(r.calls[0][1])["state"] == "cancelled"
        job = client_a.get(f"/v1/jobs/{job_id}").json()
        wait_until(lambda: client_a.get(f"/v1/jobs/{job_id}").json()["webhook"]["state"] == "delivered", 10, "state")
        assert job["state"] == "cancelled"
    finally:
        r.close()
