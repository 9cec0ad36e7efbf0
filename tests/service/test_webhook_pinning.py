"""Webhook delivery is pinned to the address the private-address check passed (``service.webhooks``): a DNS answer
that changes between the check and the connection (rebinding) cannot lead a delivery elsewhere, and the request
keeps the URL's name (``Host``; for https the SNI and the certificate's name check). Tested with real HTTP and TLS
servers on loopback and a resolver that answers differently the second time."""

from __future__ import annotations

import shutil
import socket
import ssl
import subprocess
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest

from service import webhooks

NAME = "hooks.rebind.test"


class _Receiver(BaseHTTPRequestHandler):
    seen: list[dict[str, Any]]

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers.get("content-length", "0")))
        sni = getattr(self.connection, "bonemesh_sni", None)
        type(self).seen.append({"host": self.headers["host"], "body": body, "sni": sni, "path": self.path})
        self.send_response(204)
        self.end_headers()

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture
def receiver() -> Iterator[tuple[HTTPServer, list[dict[str, Any]]]]:
    seen: list[dict[str, Any]] = []
    handler = type("Handler", (_Receiver,), {"seen": seen})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server, seen
    server.shutdown()
    server.server_close()


def _rebinding(monkeypatch: pytest.MonkeyPatch, first: str, later: str) -> list[str]:
    """``NAME`` resolves to ``first`` once, then to ``later`` (other names as usual); returns the answers given."""
    real = socket.getaddrinfo
    answers: list[str] = []

    def getaddrinfo(host: Any, port: Any, *args: Any, **kwargs: Any) -> Any:
        if host != NAME:
            return real(host, port, *args, **kwargs)
        address = first if not answers else later
        answers.append(address)
        return [(socket.AF_INET, socket.SOCK_STREAM, 6, "", (address, int(port)))]

    monkeypatch.setattr(webhooks.socket, "getaddrinfo", getaddrinfo)
    return answers


def test_a_rebinding_name_never_reaches_the_private_address(
    receiver: tuple[HTTPServer, list[dict[str, Any]]], monkeypatch: pytest.MonkeyPatch
) -> None:
    server, seen = receiver
    port = server.server_address[1]
    url = f"http://{NAME}:{port}/hook"
    # checked: a public address; then the name turns to loopback, where the receiver listens
    public = "93.184.215.14"
    answers = _rebinding(monkeypatch, public, "127.0.0.1")
    real_connect = socket.create_connection
    dialled: list[tuple[str, int]] = []

    def create_connection(address: tuple[str, int], *args: Any, **kwargs: Any) -> socket.socket:
        dialled.append(address)
        if address[0] == public:  # no network to the outside in the test: refused there
            raise ConnectionRefusedError(f"{address} refused (test)")
        return real_connect(address, *args, **kwargs)

    monkeypatch.setattr(webhooks.socket, "create_connection", create_connection)
    addresses = webhooks.vetted_addresses(url, allow_private=False)
    assert addresses == [public]
    with pytest.raises(OSError, match="refused"):
        webhooks.post(url, b"{}", {"content-type": "application/json"}, 1.0, addresses)
    assert dialled == [(public, port)] and answers == [public]  # resolved once, at the check
    assert seen == []  # loopback never reached
    # the check refuses the private answer when it is what the name resolves to now
    with pytest.raises(webhooks.CallbackRefused, match=r"127\.0\.0\.1"):
        webhooks.vetted_addresses(url, allow_private=False)


def test_the_pinned_request_keeps_the_host_header(
    receiver: tuple[HTTPServer, list[dict[str, Any]]], monkeypatch: pytest.MonkeyPatch
) -> None:
    server, seen = receiver
    port = server.server_address[1]
    url = f"http://{NAME}:{port}/hook?x=1"
    answers = _rebinding(monkeypatch, "127.0.0.1", "198.51.100.9")  # a second resolution would go nowhere
    addresses = webhooks.vetted_addresses(url, allow_private=True)
    assert webhooks.post(url, b'{"a":1}', {"content-type": "application/json"}, 5.0, addresses) == 204
    assert seen == [{"host": f"{NAME}:{port}", "body": b'{"a":1}', "sni": None, "path": "/hook?x=1"}]
    assert answers == ["127.0.0.1"]


def _certificate(folder: Path) -> tuple[Path, Path]:
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl is not installed: no certificate for the TLS receiver")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", f"/CN={NAME}",
         "-addext", f"subjectAltName=DNS:{NAME}", "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True,
    )  # fmt: skip
    return cert, key


def test_https_keeps_sni_and_the_certificate_check(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cert, key = _certificate(tmp_path)
    seen: list[dict[str, Any]] = []
    server_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server_ctx.load_cert_chain(cert, key)
    names: list[str | None] = []
    server_ctx.sni_callback = lambda sock, name, ctx: names.append(name)  # type: ignore[assignment,func-returns-value]
    handler = type("Handler", (_Receiver,), {"seen": seen})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.socket = server_ctx.wrap_socket(server.socket, server_side=True)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        port = server.server_address[1]
        _rebinding(monkeypatch, "127.0.0.1", "198.51.100.9")
        url = f"https://{NAME}:{port}/hook"
        addresses = webhooks.vetted_addresses(url, allow_private=True)
        trusted = ssl.create_default_context(cafile=str(cert))
        assert webhooks.post(url, b"{}", {}, 5.0, addresses, trusted) == 204
        assert names == [NAME] and seen[0]["host"] == f"{NAME}:{port}"
        wrong = f"https://other.rebind.test:{port}/hook"  # pinned to the same address, another name: refused
        with pytest.raises(ssl.SSLCertVerificationError):
            webhooks.post(wrong, b"{}", {}, 5.0, addresses, trusted)
    finally:
        server.shutdown()
        server.server_close()
