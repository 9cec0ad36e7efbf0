"""Request and response models of the API's PACS parts: a job from a DICOMweb series, and a job's delivery."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from core.pacs.records import is_uid
from core.params import JobParams


class DicomwebSource(BaseModel):
    """A series on a configured DICOMweb server (credentials stay in the server's settings)."""

    model_config = ConfigDict(extra="forbid")

    server: str = Field(min_length=1, max_length=64, description="a name in BONEMESH_PACS_DICOMWEB_SERVERS")
    study_uid: str = Field(description="Study Instance UID")
    series_uid: str = Field(description="Series Instance UID")

    @field_validator("study_uid", "series_uid")
    @classmethod
    def _uid(cls, value: str) -> str:
        if not is_uid(value):
            raise ValueError("expected a DICOM UID: digits and dots, at most 64 characters")
        return value


class JobSource(BaseModel):
    """Where the job's scan comes from instead of an uploaded file."""

    model_config = ConfigDict(extra="forbid")

    dicomweb: DicomwebSource


class SourceJobCreate(BaseModel):
    """``POST /v1/jobs`` with ``Content-Type: application/json``: a job on a series fetched with WADO-RS by the worker;
    the model goes back to the same server by STOW-RS unless ``deliver`` is false."""

    model_config = ConfigDict(extra="forbid")

    source: JobSource
    params: JobParams = Field(default_factory=JobParams)
    deliver: bool = Field(default=True, description="store the model back on the source server (STOW-RS)")


class Delivery(BaseModel):
    """Sending the model (Encapsulated STL) back to the PACS."""

    state: Literal["waiting", "sending", "retrying", "delivered", "failed", "none", "skipped"] = Field(
        description="waiting (for the job), sending, retrying (see error, next_attempt_at), delivered, failed (gave "
        "up), none (no destination), skipped (the job did not succeed)"
    )
    destination: dict[str, Any] | None = Field(description="DICOM node (AE title, host, port) or DICOMweb server name")
    attempts: int
    error: str | None = Field(description="the last failure")
    next_attempt_at: dt.datetime | None
    delivered_at: dt.datetime | None
    series_instance_uid: str = Field(description="the model's series, in the source study")
    sop_instance_uid: str | None = Field(
        description="the model's object; null for a label job, which sends one object per label (labels.dcm.zip), "
        "all in series_instance_uid"
    )
