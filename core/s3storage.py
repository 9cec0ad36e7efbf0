"""Job files in any S3-compatible store (AWS S3, SeaweedFS, MinIO, Ceph, R2, ...), through boto3 (the client choice
and its numbers: docs/storage.md, ``benchmarks/storage_clients.py``).

Layout under ``s3://bucket/prefix``::

    jobs/<id>/upload                      an uploaded archive (one object), or
    jobs/<id>/upload/<relative path>      a DICOM series received by the PACS gateway (one object per file)
    jobs/<id>/outputs/<version>/<name>    one published set of outputs (``publish``'s version)

An upload streams in as one multipart upload (8 MiB parts, a few in flight, never the whole scan in memory); the
store shows it only once ``CompleteMultipartUpload`` succeeds, and a refused one is aborted (nothing kept). Outputs
are written under a new version's keys, invisible to clients until the worker commits that version with the job's
outputs in the database; ``retire`` then removes the other versions (also those of attempts killed before their
commit). Credentials come from boto3's usual chain (``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, a profile, an
instance role); ``BONEMESH_S3_ENDPOINT_URL`` points at a store other than AWS (path-style addressing there).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import shutil
import uuid
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from core.s3direct import S3DirectUploads
from core.storage import (
    Storage,
    StoredFile,
    UploadTooLarge,
    UploadWriter,
    check_job_id,
    output_name_ok,
)
from engine.export.files import FILES

PART_BYTES = 8 << 20  # multipart part size (S3's minimum is 5 MiB for every part but the last)
PARTS_IN_FLIGHT = 4  # parts uploaded at once by one upload: memory stays under (4 + 1) x 8 MiB
CHUNK = 1 << 20


def make_client(endpoint_url: str | None, *, presigning: bool = False) -> Any:
    """A boto3 S3 client: SigV4, standard retries, payloads not hashed into the signature (over HTTPS that is
    boto3's default already; over a plain-HTTP endpoint hashing each part halved the upload rate,
    benchmarks/storage_clients.py); path-style addressing and checksums only when required where an endpoint is
    given (stores other than AWS)."""
    import boto3
    from botocore.config import Config

    extra: dict[str, Any] = {"s3": {"payload_signing_enabled": False}}
    if endpoint_url:
        extra = {
            "s3": {"addressing_style": "path", "payload_signing_enabled": False},
            "request_checksum_calculation": "when_required",
            "response_checksum_validation": "when_required",
        }
    if presigning:  # links for other clients (direct uploads): no checksum they would have to send
        extra["request_checksum_calculation"] = "when_required"
    config = Config(signature_version="s3v4", retries={"max_attempts": 5, "mode": "standard"}, **extra)
    region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION") or "us-east-1"
    return boto3.client("s3", endpoint_url=endpoint_url or None, region_name=region, config=config)


def _missing(exc: BaseException) -> bool:
    code = str(getattr(exc, "response", {}).get("Error", {}).get("Code", ""))
    return code in {"404", "NoSuchKey", "NotFound", "NoSuchUpload"}


class S3Storage(Storage):
    """Job files in ``s3://bucket/prefix``; local copies (the worker's input, staged outputs) under ``scratch``."""

    presigns = True

    def __init__(self, bucket: str, prefix: str = "", *, endpoint_url: str | None = None, scratch: Path) -> None:
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self.endpoint_url = endpoint_url
        self.client = make_client(endpoint_url)
        self.scratch = Path(scratch)
        self.direct = S3DirectUploads(self.client, make_client(endpoint_url, presigning=True), bucket, self.prefix)

    # -- keys -------------------------------------------------------------------------------------------------
    def _key(self, *parts: str) -> str:
        return "/".join(p for p in (self.prefix, *parts) if p)

    def _job(self, job_id: str) -> str:
        return self._key("jobs", check_job_id(job_id))

    def _keys(self, prefix: str) -> Iterator[dict[str, Any]]:
        pages = self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix)
        for page in pages:
            yield from page.get("Contents", [])

    def _delete_keys(self, keys: list[str]) -> None:
        for i in range(0, len(keys), 1000):
            batch = [{"Key": k} for k in keys[i : i + 1000]]
            self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})

    def _local(self, job_id: str, what: str) -> Path:
        folder = self.scratch / f"{check_job_id(job_id)}-{what}-{uuid.uuid4().hex[:12]}"
        folder.mkdir(parents=True)
        return folder

    # -- uploads ----------------------------------------------------------------------------------------------
    def upload_writer(self, job_id: str, max_bytes: int) -> UploadWriter:
        return _S3Upload(self.client, self.bucket, self._job(job_id) + "/upload", max_bytes)

    @contextlib.contextmanager
    def put_upload_folder(self, job_id: str, folder: Path) -> Iterator[None]:
        base = self._job(job_id) + "/upload/"
        try:
            for path in sorted(p for p in folder.rglob("*") if p.is_file()):
                self.client.upload_file(str(path), self.bucket, base + path.relative_to(folder).as_posix())
            yield
        except BaseException:
            with contextlib.suppress(Exception):
                self.delete_job(job_id)
            raise
        shutil.rmtree(folder, ignore_errors=True)

    def _upload_objects(self, job_id: str) -> list[dict[str, Any]]:
        key = self._job(job_id) + "/upload"
        return [o for o in self._keys(key) if o["Key"] == key or o["Key"].startswith(key + "/")]

    def has_upload(self, job_id: str) -> bool:
        return bool(self._upload_objects(job_id))

    @contextlib.contextmanager
    def local_upload(self, job_id: str) -> Iterator[Path]:
        folder = self._local(job_id, "input")
        try:
            upload = folder / "upload"
            key = self._job(job_id) + "/upload"
            for obj in self._upload_objects(job_id):
                dest = upload if obj["Key"] == key else upload / obj["Key"][len(key) + 1 :]
                if ".." in Path(dest.relative_to(folder)).parts:
                    raise ValueError(f"unsafe key in the store: {obj['Key']!r}")
                dest.parent.mkdir(parents=True, exist_ok=True)
                self.client.download_file(self.bucket, obj["Key"], str(dest))
            yield upload
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def inspect_path(self, job_id: str) -> contextlib.AbstractContextManager[Path]:
        return self.local_upload(job_id)

    # -- outputs ----------------------------------------------------------------------------------------------
    def staging_dir(self, job_id: str) -> Path:
        return self._local(job_id, "staging")

    def clean_staging(self, job_id: str) -> int:
        if not self.scratch.is_dir():
            return 0
        left = [p for p in self.scratch.glob(f"{check_job_id(job_id)}-*") if p.is_dir()]
        for path in left:
            shutil.rmtree(path, ignore_errors=True)
        return len(left)

    def publish(self, job_id: str, staged: Path) -> str:
        version = uuid.uuid4().hex
        base = f"{self._job(job_id)}/outputs/{version}/"
        files = [p for p in staged.iterdir() if p.is_file() and output_name_ok(p.name)]
        try:
            with ThreadPoolExecutor(max_workers=4) as pool:
                done = [
                    pool.submit(
                        self.client.upload_file,
                        str(p),
                        self.bucket,
                        base + p.name,
                        ExtraArgs={"ContentType": FILES[p.name].media_type},
                    )
                    for p in files
                ]
                for f in done:
                    f.result()
        except BaseException:
            with contextlib.suppress(Exception):
                self._delete_keys([o["Key"] for o in self._keys(base)])
            raise
        shutil.rmtree(staged, ignore_errors=True)
        return version

    def _versions(self, job_id: str) -> dict[str, list[dict[str, Any]]]:
        base = self._job(job_id) + "/outputs/"
        found: dict[str, list[dict[str, Any]]] = {}
        for obj in self._keys(base):
            version, _, name = obj["Key"][len(base) :].partition("/")
            found.setdefault(version, []).append({**obj, "Name": name})
        return found

    def retire(self, job_id: str, keep: str) -> None:
        stale = [o["Key"] for v, objs in self._versions(job_id).items() if v != keep for o in objs]
        self._delete_keys(stale)
        self._abort_output_uploads(self._job(job_id) + "/outputs/", keep=keep)

    def sweep_outputs(self, started_before: dt.datetime) -> int:
        return self._abort_output_uploads(self._key("jobs") + "/", started_before=started_before)

    def _abort_output_uploads(
        self, prefix: str, keep: str | None = None, started_before: dt.datetime | None = None
    ) -> int:
        """Abort the multipart uploads of output files under ``prefix`` (what a publish killed half way leaves: a
        large ``model.stl`` goes up in parts), but those of version ``keep`` and those begun since
        ``started_before``; returns how many."""
        aborted = 0
        for page in self.client.get_paginator("list_multipart_uploads").paginate(Bucket=self.bucket, Prefix=prefix):
            for up in page.get("Uploads", []):
                _, outputs, rest = str(up["Key"]).partition("/outputs/")
                if not outputs or (keep is not None and rest.partition("/")[0] == keep):
                    continue
                initiated = up.get("Initiated")
                if started_before is not None:
                    if not isinstance(initiated, dt.datetime):
                        continue
                    if (initiated if initiated.tzinfo else initiated.replace(tzinfo=dt.UTC)) >= started_before:
                        continue
                with contextlib.suppress(Exception):  # gone meanwhile (completed or aborted elsewhere)
                    self.client.abort_multipart_upload(Bucket=self.bucket, Key=up["Key"], UploadId=up["UploadId"])
                    aborted += 1
        return aborted

    def _version(self, job_id: str, version: str | None) -> str | None:
        """``version``, or (for a caller without the job's record) the newest one in the store."""
        if version is not None:
            return version
        versions = self._versions(job_id)
        if not versions:
            return None
        return max(versions, key=lambda v: max(o["LastModified"] for o in versions[v]))

    def _output_key(self, job_id: str, name: str, version: str | None) -> str | None:
        if not output_name_ok(name):
            return None
        v = self._version(job_id, version)
        return None if v is None else f"{self._job(job_id)}/outputs/{v}/{name}"

    def output(self, job_id: str, name: str, version: str | None = None) -> StoredFile | None:
        key = self._output_key(job_id, name, version)
        if key is None:
            return None
        try:
            head = self.client.head_object(Bucket=self.bucket, Key=key)
        except Exception as exc:
            if _missing(exc):
                return None
            raise
        return StoredFile(name, int(head["ContentLength"]), str(head.get("ETag", "")).strip('"'))

    def read_output(self, job_id: str, name: str, version: str | None = None) -> bytes | None:
        key = self._output_key(job_id, name, version)
        if key is None:
            return None
        try:
            return bytes(self.client.get_object(Bucket=self.bucket, Key=key)["Body"].read())
        except Exception as exc:
            if _missing(exc):
                return None
            raise

    def open_output(self, job_id: str, name: str, version: str | None = None) -> Iterator[bytes]:
        key = self._output_key(job_id, name, version)
        if key is None:
            raise FileNotFoundError(name)
        try:
            body = self.client.get_object(Bucket=self.bucket, Key=key)["Body"]
        except Exception as exc:
            if _missing(exc):
                raise FileNotFoundError(name) from None
            raise
        try:
            yield from body.iter_chunks(CHUNK)
        finally:
            body.close()

    @contextlib.contextmanager
    def local_output(self, job_id: str, name: str, version: str | None = None) -> Iterator[Path | None]:
        key = self._output_key(job_id, name, version)
        if key is None or self.output(job_id, name, version) is None:
            yield None
            return
        folder = self._local(job_id, "output")
        try:
            path = folder / name
            self.client.download_file(self.bucket, key, str(path))
            yield path
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def copy_outputs(self, job_id: str, version: str | None, into: Path) -> list[str]:
        v = self._version(job_id, version)
        names = []
        for obj in self._versions(job_id).get(v or "", []):
            if output_name_ok(obj["Name"]):
                self.client.download_file(self.bucket, obj["Key"], str(into / obj["Name"]))
                names.append(obj["Name"])
        return names

    def output_url(self, job_id: str, name: str, version: str | None, ttl_seconds: int) -> str | None:
        key = self._output_key(job_id, name, version)
        if key is None:
            return None
        params = {
            "Bucket": self.bucket,
            "Key": key,
            "ResponseContentType": FILES[name].media_type,
            "ResponseContentDisposition": f'attachment; filename="{name}"',
        }
        return str(self.client.generate_presigned_url("get_object", Params=params, ExpiresIn=ttl_seconds))

    # -- the rest ---------------------------------------------------------------------------------------------
    def delete_job(self, job_id: str) -> None:
        base = self._job(job_id) + "/"
        self._delete_keys([o["Key"] for o in self._keys(base)])
        pages = self.client.get_paginator("list_multipart_uploads").paginate(Bucket=self.bucket, Prefix=base)
        for page in pages:
            for up in page.get("Uploads", []):
                with contextlib.suppress(Exception):
                    self.client.abort_multipart_upload(Bucket=self.bucket, Key=up["Key"], UploadId=up["UploadId"])
        self.clean_staging(job_id)

    def ping(self) -> None:
        key = self._key(f".ping-{uuid.uuid4().hex}")
        self.client.put_object(Bucket=self.bucket, Key=key, Body=b"ok")
        self.client.delete_object(Bucket=self.bucket, Key=key)

    def free_bytes(self) -> int | None:
        return None

    def local_paths(self, job_id: str) -> dict[str, str]:
        return {str(self.scratch): "the worker's scratch folder"}


class _S3Upload(UploadWriter):
    """One upload streamed into a multipart upload (started with the first full part; a small upload is one PUT)."""

    def __init__(self, client: Any, bucket: str, key: str, max_bytes: int) -> None:
        self.client, self.bucket, self.key, self.max_bytes = client, bucket, key, max_bytes
        self.size = 0
        self.buf = bytearray()
        self.upload_id: str | None = None
        self.parts: list[Future[dict[str, Any]]] = []
        self.pool: ThreadPoolExecutor | None = None

    def write(self, chunk: bytes | memoryview) -> None:
        self.size += len(chunk)
        if self.size > self.max_bytes:
            self.abort()
            raise UploadTooLarge(f"the upload is larger than the limit of {self.max_bytes:,} bytes")
        self.buf += chunk
        while len(self.buf) >= PART_BYTES:
            self._send(bytes(self.buf[:PART_BYTES]))
            del self.buf[:PART_BYTES]

    def _send(self, body: bytes) -> None:
        if self.upload_id is None:
            self.upload_id = self.client.create_multipart_upload(Bucket=self.bucket, Key=self.key)["UploadId"]
            self.pool = ThreadPoolExecutor(max_workers=PARTS_IN_FLIGHT, thread_name_prefix="s3-part")
        assert self.pool is not None
        for done in (f for f in self.parts if f.done()):
            done.result()  # a part that failed stops the upload now, not at commit
        in_flight = [f for f in self.parts if not f.done()]
        if len(in_flight) >= PARTS_IN_FLIGHT:
            in_flight[0].result()
        number = len(self.parts) + 1
        self.parts.append(self.pool.submit(self._part, number, body))

    def _part(self, number: int, body: bytes) -> dict[str, Any]:
        r = self.client.upload_part(
            Bucket=self.bucket, Key=self.key, UploadId=self.upload_id, PartNumber=number, Body=body
        )
        return {"PartNumber": number, "ETag": r["ETag"]}

    def commit(self) -> None:
        if self.upload_id is None:
            self.client.put_object(Bucket=self.bucket, Key=self.key, Body=bytes(self.buf))
            self.buf = bytearray()
            return
        try:
            if self.buf:
                self._send(bytes(self.buf))
                self.buf = bytearray()
            parts = [f.result() for f in self.parts]
            self.client.complete_multipart_upload(
                Bucket=self.bucket, Key=self.key, UploadId=self.upload_id, MultipartUpload={"Parts": parts}
            )
        except BaseException:
            self.abort()
            raise
        self._close_pool()

    def abort(self) -> None:
        self.buf = bytearray()
        upload_id, self.upload_id = self.upload_id, None
        self._close_pool()
        if upload_id is not None:
            with contextlib.suppress(Exception):
                self.client.abort_multipart_upload(Bucket=self.bucket, Key=self.key, UploadId=upload_id)

    def _close_pool(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None


def create_bucket(settings: Any = None) -> str:
    """Make the bucket of ``BONEMESH_STORAGE_URL`` (an ``s3://`` URL) if it is not there yet; returns what it did.
    For a first start of a store (docker-compose's ``s3-init``); on AWS, make buckets with your usual tooling.

    Raises:
        ValueError: the storage URL is not an S3 one.
    """
    from core.settings import get_settings

    settings = settings or get_settings()
    kind, where = settings.storage_location()
    if kind != "s3":
        raise ValueError("BONEMESH_STORAGE_URL is not an s3:// URL: there is no bucket to make")
    bucket = where.split("/", 1)[0]
    client = make_client(settings.s3_endpoint_url)
    try:
        client.head_bucket(Bucket=bucket)
        return f"bucket {bucket} exists"
    except Exception as exc:
        if not _missing(exc):
            raise
    client.create_bucket(Bucket=bucket)
    return f"bucket {bucket} made"


if __name__ == "__main__":  # python -m core.s3storage create-bucket
    import sys

    if sys.argv[1:] != ["create-bucket"]:
        raise SystemExit("usage: python -m core.s3storage create-bucket")
    print(create_bucket())  # noqa: T201 - the one line of a one-shot container
