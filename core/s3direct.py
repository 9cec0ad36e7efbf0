"""Direct uploads to an S3 store (``Storage.direct`` of ``core.s3storage.S3Storage``): the client PUTs the parts of
one multipart upload of ``jobs/<id>/upload`` through presigned ``UploadPart`` links, so the API never carries the
scan's bytes (``service.direct`` hands out the links and completes the upload).

The links are SigV4 query-string signatures of ``PUT`` with ``uploadId`` and ``partNumber``; the only header signed
is Host (``X-Amz-SignedHeaders=host``), and the payload is not (``UNSIGNED-PAYLOAD``). Content-Type is never
signed, so a client whose HTTP library adds its own still matches; ``PartLink.headers`` lists every header the
client must send, and with these links there is none. Checksums are left to the client (not requested by the
signature): a browser cannot compute a CRC of a part before it sends it.
"""

from __future__ import annotations

import contextlib
import datetime as dt
from typing import Any
from urllib.parse import parse_qs, urlsplit

from core.storage import DirectUploads, PartLink, StoredPart, check_job_id


def signed_headers(url: str) -> list[str]:
    """The headers a presigned URL's signature covers (``X-Amz-SignedHeaders``)."""
    query = parse_qs(urlsplit(url).query)
    return [h for h in (query.get("X-Amz-SignedHeaders") or [""])[0].split(";") if h]


def _missing_upload(exc: BaseException) -> bool:
    code = str(getattr(exc, "response", {}).get("Error", {}).get("Code", ""))
    return code in {"404", "NoSuchUpload", "NoSuchKey", "NotFound"}


class S3DirectUploads(DirectUploads):
    """Direct uploads into ``bucket`` under ``prefix``, with ``client`` (boto3) and ``signer`` (a boto3 client that
    never asks for checksums in what it presigns)."""

    def __init__(self, client: Any, signer: Any, bucket: str, prefix: str) -> None:
        self.client, self.signer, self.bucket, self.prefix = client, signer, bucket, prefix

    def _key(self, job_id: str) -> str:
        return "/".join(p for p in (self.prefix, "jobs", check_job_id(job_id), "upload") if p)

    def begin(self, job_id: str) -> str:
        return str(self.client.create_multipart_upload(Bucket=self.bucket, Key=self._key(job_id))["UploadId"])

    def part_links(self, job_id: str, upload_id: str, count: int, ttl_seconds: int) -> list[PartLink]:
        links = []
        for number in range(1, count + 1):
            params = {"Bucket": self.bucket, "Key": self._key(job_id), "UploadId": upload_id, "PartNumber": number}
            url = str(self.signer.generate_presigned_url("upload_part", Params=params, ExpiresIn=ttl_seconds))
            extra = [h for h in signed_headers(url) if h != "host"]
            if extra:  # never with this signer; a client could not know what to send
                raise RuntimeError(f"the presigned part link signs headers besides Host: {extra}")
            links.append(PartLink(number, url, {}))
        return links

    def parts(self, job_id: str, upload_id: str) -> list[StoredPart]:
        found: list[StoredPart] = []
        pages = self.client.get_paginator("list_parts").paginate(
            Bucket=self.bucket, Key=self._key(job_id), UploadId=upload_id
        )
        try:
            for page in pages:
                for part in page.get("Parts", []):
                    found.append(StoredPart(int(part["PartNumber"]), str(part["ETag"]), int(part["Size"])))
        except Exception as exc:
            if _missing_upload(exc):
                raise FileNotFoundError(f"no upload {upload_id}") from None
            raise
        return sorted(found, key=lambda p: p.number)

    def complete(self, job_id: str, upload_id: str, parts: list[tuple[int, str]]) -> None:
        listed = [{"PartNumber": n, "ETag": etag if etag.startswith('"') else f'"{etag}"'} for n, etag in parts]
        try:
            self.client.complete_multipart_upload(
                Bucket=self.bucket, Key=self._key(job_id), UploadId=upload_id, MultipartUpload={"Parts": listed}
            )
        except Exception as exc:
            response = getattr(exc, "response", None)
            if response is None:
                raise
            error = response.get("Error", {})
            raise ValueError(f"the store refused the parts: {error.get('Code')}: {error.get('Message')}") from None

    def abort(self, job_id: str, upload_id: str) -> None:
        with contextlib.suppress(Exception):
            self.client.abort_multipart_upload(Bucket=self.bucket, Key=self._key(job_id), UploadId=upload_id)

    def pending(self, started_before: Any) -> list[tuple[str, str]]:
        base = "/".join(p for p in (self.prefix, "jobs") if p) + "/"
        found = []
        for page in self.client.get_paginator("list_multipart_uploads").paginate(Bucket=self.bucket, Prefix=base):
            for up in page.get("Uploads", []):
                job_id, _, rest = up["Key"][len(base) :].partition("/")
                initiated = up.get("Initiated")
                if rest != "upload" or not isinstance(initiated, dt.datetime):
                    continue
                if initiated.tzinfo is None:
                    initiated = initiated.replace(tzinfo=dt.UTC)
                if initiated < started_before and not self._active(up["Key"], str(up["UploadId"]), started_before):
                    found.append((job_id, str(up["UploadId"])))
        return found

    def _active(self, key: str, upload_id: str, since: dt.datetime) -> bool:
        """Whether a part arrived since ``since`` (an upload through the API still streaming in, not a leftover)."""
        try:
            parts = self.client.list_parts(Bucket=self.bucket, Key=key, UploadId=upload_id).get("Parts", [])
        except Exception:
            return False
        stamps = [p["LastModified"] for p in parts if isinstance(p.get("LastModified"), dt.datetime)]
        return any((t if t.tzinfo else t.replace(tzinfo=dt.UTC)) >= since for t in stamps)
