"""Response headers of the API, and their OpenAPI declarations (``responses={200: {"headers": ...}}``): ``Location``
of what a request made, ``ETag`` / ``Cache-Control`` / ``Retry-After`` of a polled job, ``Idempotent-Replayed``.

Polling a job (``GET /v1/jobs/{id}``): the answer carries a weak ``ETag`` of what the job says (state, stage,
progress, outputs, errors, runs, webhook and delivery: not the download links, which are signed afresh on each
read), ``Cache-Control: private, no-cache`` (a client may keep it, and asks again with ``If-None-Match``: 304 while
nothing changed) and, while the job is queued or running (or being re-oriented), ``Retry-After``: the seconds after
which asking again is worth it. The ETag also changes every half link lifetime (``BONEMESH_URL_TTL_SECONDS`` / 2)
for a job with outputs, so the links of a body kept under a 304 still work.
"""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

from core.db import ORIENTING, Job

CACHE_JOB = "private, no-cache"  # keep it, but ask again (If-None-Match) before using it
POLL_SECONDS = {"queued": 5, "running": 2, ORIENTING: 2}  # Retry-After while the job still changes

LOCATION = {"Location": {"description": "the path of what the request made", "schema": {"type": "string"}}}
ETAG = {
    "ETag": {
        "description": "weak validator of the job's state (links excluded): send it in If-None-Match, 304 while the "
        "job is unchanged",
        "schema": {"type": "string"},
    }
}
CACHE_CONTROL = {
    "Cache-Control": {
        "description": "private, no-cache: a client may keep the answer, and revalidates it with If-None-Match",
        "schema": {"type": "string"},
    }
}
RETRY_AFTER = {
    "Retry-After": {
        "description": "while the job is queued (5) or running (2): the seconds after which polling again is worth it; "
        "absent once it has finished",
        "schema": {"type": "integer", "minimum": 0},
    }
}
REPLAYED = {
    "Idempotent-Replayed": {
        "description": "true when this is the answer to an earlier request with the same Idempotency-Key (nothing new "
        "was made)",
        "schema": {"type": "string", "enum": ["true"]},
    }
}
JOB_HEADERS = {**ETAG, **CACHE_CONTROL, **RETRY_AFTER}
CREATED = {**LOCATION, **REPLAYED}
IN_USE = {
    "Retry-After": {
        "description": "with 409 idempotency_key_in_use: the seconds after which to send the request again",
        "schema": {"type": "integer", "minimum": 0},
    }
}
DOWNLOAD = {
    name: {"description": text, "schema": {"type": "string"}}
    for name, text in (
        ("ETag", "the file's validator: send it in If-None-Match, 304 while unchanged"),
        ("Cache-Control", "private, max-age up to the link's expiry"),
        ("Expires", "the link's expiry (HTTP date)"),
        ("Content-Disposition", 'attachment; filename="<the output\'s name>"'),
    )
}
NOT_MODIFIED = {"description": "not modified: the ETag in If-None-Match is still the job's", "headers": JOB_HEADERS}


def job_etag(body: dict[str, Any], link_ttl: int, now: float | None = None) -> str:
    """The weak ETag of a job resource (``JobOut`` as JSON): its content without the signed links and their expiry;
    with outputs, the half link lifetime it is read in."""
    content = dict(body)
    outputs = content.get("outputs")
    if outputs:
        content["outputs"] = [{k: v for k, v in o.items() if k not in ("url", "expires_at")} for o in outputs]
        content["links_epoch"] = int((time.time() if now is None else now) // max(1, link_ttl // 2))
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), default=str)
    return 'W/"' + hashlib.sha256(text.encode()).hexdigest()[:32] + '"'


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """Whether ``If-None-Match`` names ``etag`` (weak comparison, RFC 9110) or is ``*``."""
    if if_none_match is None:
        return False
    if if_none_match.strip() == "*":
        return True
    bare = etag.removeprefix("W/")
    return any(tag.strip().removeprefix("W/") == bare for tag in if_none_match.split(","))


def job_headers(job: Job, etag: str) -> dict[str, str]:
    """``ETag``, ``Cache-Control`` and, while the job still changes, ``Retry-After``."""
    headers = {"ETag": etag, "Cache-Control": CACHE_JOB}
    wait = POLL_SECONDS.get(job.state) or (POLL_SECONDS[ORIENTING] if job.stage == ORIENTING else None)
    if wait is not None:
        headers["Retry-After"] = str(wait)
    return headers
