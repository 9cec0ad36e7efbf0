"""PACS settings, from ``BONEMESH_PACS_*`` environment variables (JSON for the structured ones).

There is no "accept everything" default: with an empty ``BONEMESH_PACS_ALLOW`` every association is rejected and
``bonemesh pacs`` refuses to start. Credentials of DICOMweb servers live only here; jobs refer to a server by name.
"""

from __future__ import annotations

import re
from functools import lru_cache
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from core.pacs.routing import DEFAULT_RULES, Rule

_AE = re.compile(r"^[\x20-\x5b\x5d-\x7e]{1,16}$")  # AE title: 16 printable characters, no backslash


def check_ae_title(value: str) -> str:
    """An AE title as DICOM allows it (1-16 characters, no backslash or control character), stripped."""
    value = value.strip()
    if not _AE.match(value):
        raise ValueError(f"Expected an AE title of 1-16 printable characters without backslash, got {value!r}")
    return value


class DicomNode(BaseModel):
    """A DICOM application entity: where C-STORE sends the model."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["dicom"] = "dicom"
    ae_title: str
    host: str
    port: int = Field(ge=1, le=65535)

    _ae = field_validator("ae_title")(check_ae_title)


class DicomwebTarget(BaseModel):
    """A configured DICOMweb server (by name) that receives the model by STOW-RS."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["dicomweb"] = "dicomweb"
    server: str


class DicomwebServer(BaseModel):
    """A DICOMweb server: base URL (of QIDO/WADO/STOW-RS) and its credentials (HTTP basic auth or a bearer token)."""

    model_config = ConfigDict(extra="forbid")

    url: str
    username: str | None = None
    password: SecretStr | None = None
    token: SecretStr | None = None
    timeout_seconds: float = Field(default=60.0, gt=0)
    attempts: int = Field(
        default=3,
        ge=1,
        le=10,
        description="tries of a request that failed for a transient reason (no connection, a time-out, HTTP 429 "
        "or 5xx, an answer cut short)",
    )
    backoff_seconds: float = Field(default=0.5, ge=0, le=60, description="wait before the second try, doubling after")


class AllowEntry(BaseModel):
    """One allow-list entry: a calling AE title, optionally bound to a source address (``AE@10.0.0.5``)."""

    ae_title: str
    address: str | None = None

    def admits(self, ae_title: str, address: str) -> bool:
        """Whether a caller with this AE title from this address matches the entry."""
        return ae_title.strip() == self.ae_title and (self.address is None or self.address == address)


class PacsSettings(BaseSettings):
    """All PACS settings; each field ``name`` is read from ``BONEMESH_PACS_NAME``."""

    model_config = SettingsConfigDict(env_prefix="BONEMESH_PACS_", extra="ignore", env_ignore_empty=True)

    ae_title: str = Field(default="BONEMESH", description="this node's AE title (the called AE of senders)")
    host: str = Field(default="127.0.0.1", description="address the storage SCP listens on (0.0.0.0: all)")
    port: int = Field(default=11112, ge=1, le=65535)
    allow: Annotated[list[AllowEntry], NoDecode] = Field(
        default_factory=list, description="calling AE titles allowed to store, comma-separated, each AE or AE@address"
    )
    stable_seconds: float = Field(default=60.0, gt=0, description="a series is complete this long after its last image")
    reference_wait_seconds: float = Field(
        default=600.0,
        ge=0,
        description="how long a received SEG waits for the CT series it references to arrive (then its job fails "
        "saying the series is missing)",
    )
    keep_unrouted_seconds: float = Field(
        default=86400.0,
        ge=0,
        description="how long a received CT series that no rule takes is kept for a SEG drawn on it (0: dropped at "
        "once)",
    )
    routes: list[Rule] = Field(default_factory=lambda: list(DEFAULT_RULES))
    destination: DicomNode | DicomwebTarget | None = Field(
        default=None, discriminator="kind", description="where models of C-STORE jobs go (none: not sent back)"
    )
    dicomweb_servers: dict[str, DicomwebServer] = Field(default_factory=dict)
    owner_key: SecretStr | None = Field(
        default=None, description="API key whose holders see the C-STORE jobs (default: the first BONEMESH_API_KEYS)"
    )
    delivery_backoff_seconds: float = Field(default=5.0, gt=0)
    delivery_max_backoff_seconds: float = Field(default=600.0, gt=0)
    delivery_max_attempts: int = Field(default=30, ge=1)
    poll_seconds: float = Field(
        default=1.0, gt=0, description="how often stable series and due deliveries are looked for"
    )

    _ae = field_validator("ae_title")(check_ae_title)

    @field_validator("allow", mode="before")
    @classmethod
    def _split_allow(cls, value: Any) -> Any:
        if isinstance(value, str):
            entries = []
            for item in (v.strip() for v in value.split(",")):
                if item:
                    ae, _, address = item.partition("@")
                    entries.append({"ae_title": check_ae_title(ae), "address": address.strip() or None})
            return entries
        return value

    @model_validator(mode="after")
    def _known_server(self) -> PacsSettings:
        if isinstance(self.destination, DicomwebTarget) and self.destination.server not in self.dicomweb_servers:
            raise ValueError(
                f"BONEMESH_PACS_DESTINATION names DICOMweb server {self.destination.server!r}, "
                f"which is not in BONEMESH_PACS_DICOMWEB_SERVERS ({sorted(self.dicomweb_servers)})"
            )
        return self

    def admits(self, ae_title: str, address: str) -> bool:
        """Whether a calling AE (from ``address``) is on the allow-list."""
        return any(entry.admits(ae_title, address) for entry in self.allow)


@lru_cache(maxsize=1)
def get_pacs_settings() -> PacsSettings:
    """The PACS settings of this process (read from the environment once)."""
    return PacsSettings()
