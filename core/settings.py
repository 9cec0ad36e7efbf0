"""Settings of the service and the worker, from ``BONEMESH_*`` environment variables (one object, read once).

Embedded defaults run on one machine with nothing else installed but Redis: job records in SQLite under the data
folder, files on local disk, the worker on the CPU when no GPU is present.
"""

from __future__ import annotations

import os
import secrets
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

DEV_API_KEY = "bonemesh-dev-key"


class Settings(BaseSettings):
    """All settings; each field ``name`` is read from ``BONEMESH_NAME``."""

    model_config = SettingsConfigDict(env_prefix="BONEMESH_", extra="ignore")

    redis_url: str = "redis://127.0.0.1:6379/0"
    data_dir: Path = Path("bonemesh-data")
    database_url: str | None = Field(default=None, description="SQLAlchemy URL; default SQLite in data_dir")
    storage_url: str | None = Field(
        default=None,
        description="where uploads and outputs live: file:///path or s3://bucket/prefix (docs/storage.md); "
        "default: the data folder",
    )
    s3_endpoint_url: str | None = Field(
        default=None, description="the S3 API's URL for a store other than AWS (SeaweedFS, MinIO, R2, ...)"
    )
    download_links: Literal["api", "store"] = Field(
        default="api",
        description="download links: api (the API's signed /v1/files links) or store (the S3 store's presigned "
        "URLs, expiring with url_ttl_seconds; S3 storage only)",
    )
    scratch_dir: Path | None = Field(
        default=None, description="the worker's local copies of S3 inputs and staged outputs; default data_dir/scratch"
    )
    api_keys: Annotated[list[str], NoDecode] = Field(default_factory=lambda: [DEV_API_KEY])
    secret_key: str | None = Field(default=None, description="signs download links; default: a key file in data_dir")
    device: str = "auto"
    max_device_bytes: str | None = Field(
        default=None,
        description="device memory budget per job (e.g. 8GiB): every stage keeps to it, so workers can share a GPU "
        "and any scan size fits; default none",
    )
    max_upload_bytes: int = 4 << 30
    active_uploads: int = Field(
        default=4, ge=1, description="upload bodies read at once; more wait unread, so status reads stay fast"
    )
    url_ttl_seconds: int = 3600
    upload_ttl_seconds: int = Field(
        default=86400,
        ge=1,
        le=7 * 86400,
        description="direct uploads (S3): how long the part links work; an upload not completed by then is aborted",
    )
    idempotency_ttl_seconds: int = Field(
        default=86400,
        ge=60,
        le=30 * 86400,
        description="how long an Idempotency-Key of POST /v1/jobs or /v1/uploads is remembered (then it may be reused)",
    )
    queue: str = "bonemesh"
    stale_seconds: float = 60.0
    reconcile_seconds: float = 15.0
    heartbeat_seconds: float = 2.0
    decode_threads: int | None = Field(
        default=None, ge=1, description="threads (DICOM: processes) decoding an upload; default: the worker's CPUs"
    )
    decode_processes: bool | None = Field(
        default=None, description="DICOM in processes: true, false; unset: for 64+ files on 4+ CPUs (engine.io)"
    )
    warmup: Literal["auto", "true", "false"] = Field(
        default="auto",
        description="the worker warms its device up with one small job before taking any (auto, true: on every "
        "device; false: its first job pays for it, 1-2 s)",
    )
    warmup_volume_bytes: int = Field(
        default=512 << 20,
        description="a CUDA worker's warm-up also page-locks its load buffers for a volume this size (16-bit: 2 bytes "
        "a voxel; a 476 x 1024 x 1024 scan is 952 MiB), so the first scan up to it does not pay for them; 0: the "
        "first job that needs them does",
    )
    png_decoder: Literal["auto", "libpng", "pillow"] = Field(
        default="auto",
        description="auto: plain grayscale PNG inflated on the host and unfiltered on the job's GPU (on a CPU: "
        "libpng); libpng: libpng on the host; pillow: every PNG through Pillow (slower)",
    )
    decode_during_upload: bool = Field(
        default=True,
        description="a zip of PNG slices uploaded through the API is decoded while it arrives, into a volume file "
        "beside the upload that the worker loads instead of decoding the zip (engine.io.predecode; only inflated, "
        "for the worker's GPU to unfilter, unless BONEMESH_DEVICE is cpu or BONEMESH_PNG_DECODER is not auto); "
        "local storage only (on S3 it is not made: the worker decodes the zip)",
    )
    predecode_min_bytes: int = Field(
        default=64 << 20,
        ge=0,
        description="only uploads of at least this many bytes (by the request's length; one of unknown length too) "
        "are decoded while they arrive: a smaller scan's slices cost its worker less than the decoding process costs "
        "the upload (a clinical CT of 6.8 MB: 0.09 s of the worker's loading, against 0.1-0.7 s more per upload, "
        "4 at once; docs/benchmarks.md); 0: every upload",
    )
    predecode_threads: int | None = Field(
        default=None,
        ge=1,
        le=64,
        description="threads of the API decoding one upload's slices as it arrives; "
        "default: the API process's CPUs (engine.io.parallel.decode_threads)",
    )
    predecode_process: bool = Field(
        default=True,
        description="the API decodes an upload's slices as it arrives in a child process of its own (one per "
        "upload, one started ahead), so the decoding does not share the API process with the upload's receiving; "
        "false: on threads of the API process (engine.io.predecode_proc)",
    )
    predecode_wait_seconds: float = Field(
        default=60.0,
        gt=0,
        description="the API waits this long for the decoding process's verdict once an upload is complete; past "
        "it the decoded slices are dropped and the worker decodes the zip",
    )
    outage_seconds: float = Field(
        default=60.0,
        ge=0,
        description="a worker retries a store or database call this long (backoff with jitter) before it re-queues "
        "the job; 0: at once",
    )
    outage_requeues: int = Field(
        default=3, ge=0, le=100, description="a job re-queued this often for an outage fails with its code"
    )
    job_soft_time_limit: int = 3600
    job_time_limit: int = 3900
    max_attempts: int = 3
    public_url: str | None = Field(default=None, description="base URL of download links (default: the request's)")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="browser origins allowed to call the API (CORS); empty: none"
    )
    webhook_allow_private: bool = Field(
        default=False, description="accept callback URLs on loopback, link-local and private addresses (tests only)"
    )
    webhook_retry_seconds: float = Field(default=6 * 3600, ge=0, description="how long a webhook is retried")
    webhook_backoff_seconds: float = Field(default=5.0, gt=0, description="first retry delay; doubles each time")
    webhook_timeout_seconds: float = Field(default=10.0, gt=0, description="one delivery's time limit")
    webhook_poll_seconds: float = Field(default=1.0, gt=0, description="how often due webhooks are looked for")
    assets_dir: Path | None = Field(
        default=None, description="the page's npm packages (node_modules); default: beside the service's source"
    )

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        if isinstance(value, str):
            return [o.strip().rstrip("/") for o in value.split(",") if o.strip()]
        return value

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_keys(cls, value: object) -> object:
        if isinstance(value, str):
            return [k.strip() for k in value.split(",") if k.strip()]
        return value

    @field_validator("api_keys")
    @classmethod
    def _some_key(cls, value: list[str]) -> list[str]:
        if not value:
            raise ValueError("BONEMESH_API_KEYS holds no key")
        return value

    @field_validator("warmup_volume_bytes", mode="before")
    @classmethod
    def _byte_count(cls, value: object) -> object:
        """``512MiB``, ``1GiB``, a plain count or 0, read once here (ValueError: not a byte count)."""
        from engine.budget import parse_bytes

        return (parse_bytes(value) or 0) if isinstance(value, str | int) else value

    @field_validator("storage_url")
    @classmethod
    def _storage_scheme(cls, value: str | None) -> str | None:
        if value is not None and not value.startswith(("file://", "s3://")):
            raise ValueError("BONEMESH_STORAGE_URL must be file:///path or s3://bucket/prefix")
        if value is not None and value.startswith("s3://") and not value[5:].split("/", 1)[0]:
            raise ValueError("BONEMESH_STORAGE_URL s3://bucket/prefix names no bucket")
        return value

    def storage_location(self) -> tuple[Literal["file", "s3"], str]:
        """("file", folder) or ("s3", "bucket/prefix") from ``BONEMESH_STORAGE_URL`` (default: the data folder)."""
        url = self.storage_url or ""
        if url.startswith("s3://"):
            return "s3", url[5:].strip("/")
        if url.startswith("file://"):
            from urllib.parse import unquote, urlparse

            return "file", unquote(urlparse(url).path)
        return "file", str(self.data_dir)

    def scratch_root(self) -> Path:
        """The worker's (and the API's) private local folder for copies from the store."""
        return self.scratch_dir or self.data_dir / "scratch"

    @property
    def db_url(self) -> str:
        """The database URL (SQLite file in the data folder unless ``BONEMESH_DATABASE_URL`` is set)."""
        return self.database_url or f"sqlite:///{(self.data_dir / 'bonemesh.db').resolve()}"

    def signing_key(self) -> bytes:
        """``BONEMESH_SECRET_KEY``, or a random key kept in ``data_dir/secret.key`` (created once, mode 600)."""
        if self.secret_key:
            return self.secret_key.encode()
        path = self.data_dir / "secret.key"
        if not path.exists():
            self.data_dir.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{secrets.token_hex(4)}.tmp")
            tmp.write_text(secrets.token_hex(32))
            tmp.chmod(0o600)
            try:
                os.link(tmp, path)  # first writer wins; a concurrent process reads the same key
            except FileExistsError:
                pass
            finally:
                tmp.unlink()
        return path.read_text().strip().encode()


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The settings of this process (read from the environment once)."""
    return Settings()
