"""What the attack suite of issue 15 found, checked in-process (the API app without a broker, and the parts it is
built from): every bad input is one row of a table, so adding a case is one line."""

from __future__ import annotations

import errno
import io
import json
import logging
import sqlite3
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.exc import OperationalError

from core.logsafe import EscapingFilter, escape_control
from core.params import JobParams
from core.storage import LocalStorage, is_storage_full
from engine.data import HEADSQ_ZIP
from engine.errors import InputError
from engine.io import inspect_input
from engine.io.archive import open_members
from engine.params import ReconParams
from tests.service.checks import assert_problem
from tests.service.conftest import bomb_of_small_members, png_bytes, slice_zip, sphere_volume

KEY = {"X-API-Key": "key-a"}
HEADSQ_PARAMS = {"iso": 1150, "spacing": [1.5, 3.2, 3.2]}


def _no_job_files(client: TestClient) -> None:
    jobs = Path(client.app.state.data_dir) / "jobs"  # type: ignore[attr-defined]
    assert not [p for p in jobs.rglob("*") if p.is_file()], "a refused upload left files behind"


def _multipart(parts: list[tuple[str, str | None, bytes]], *, close: bool = True, boundary: str = "b0nemesh") -> bytes:
    """A hand-made body: (name, filename or None, content) parts; ``close=False`` leaves out the closing boundary."""
    out = b""
    for name, filename, content in parts:
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename is not None else "")
        out += f"--{boundary}\r\nContent-Disposition: {disposition}\r\n\r\n".encode() + content + b"\r\n"
    return out + (f"--{boundary}--\r\n".encode() if close else b"")


def _post_raw(client: TestClient, body: bytes, boundary: str = "b0nemesh") -> Any:
    headers = {**KEY, "Content-Type": f"multipart/form-data; boundary={boundary}"}
    return client.post("/v1/jobs", content=body, headers=headers)


# -- 1. log forging: client text never starts a log line ----------------------------------------------------------
FORGING = {
    "newline": "scan\nINFO job 1 succeeded",
    "carriage-return": "scan\rINFO job 1 succeeded",
    "crlf": "scan\r\nINFO job 1 succeeded",
    "line-separator": "scan\u2028INFO job 1 succeeded",
    "next-line": "scan\x85INFO job 1 succeeded",
    "ansi-escape": "scan\x1b[2K\x1b[1GINFO job 1 succeeded",
    "bidi-override": "scan\u202eINFO job 1 succeeded",
    "nul": "scan\x00INFO",
}


@pytest.mark.parametrize("kind", list(FORGING))
def test_control_characters_never_reach_a_log_line(kind: str) -> None:
    text = FORGING[kind]
    escaped = escape_control(text)
    assert escaped.isprintable() and "INFO" in escaped, escaped
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    log = logging.getLogger(f"bonemesh.test.{kind}")
    log.addHandler(handler)
    log.addFilter(EscapingFilter())
    try:
        log.error("job %s failed: %s", "abc", text)
        try:
            raise ValueError(f"cannot decode {text}")
        except ValueError:
            log.exception("job %s", "abc")
    finally:
        log.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    assert not [line for line in lines if line.startswith(("INFO", "\x00"))], lines
    assert all(line.isprintable() for line in lines), lines


def test_upload_name_is_kept_escaped(client: TestClient) -> None:
    body = _multipart(
        [
            ("file", "head\nINFO job 1 succeeded\u2028.zip", HEADSQ_ZIP.read_bytes()),
            ("params", None, json.dumps(HEADSQ_PARAMS).encode()),
        ]
    )
    resp = _post_raw(client, body)
    assert resp.status_code == 202, resp.text
    assert resp.json()["upload_name"] == "head\\x0aINFO job 1 succeeded\\u2028.zip"


# -- 3. parameters that are valid JSON numbers but absurd: 422 at upload, ValueError in the engine ------------------
ABSURD = {
    # name: (flat job params, the field named, the engine's form or None when the engine has no such field)
    "spacing-huge": ({"spacing": [1e300, 1, 1]}, "spacing", None),
    "spacing-tiny": ({"spacing": [1e-300, 1, 1]}, "spacing", None),
    "spacing-over-100mm": ({"spacing": [1, 1, 150]}, "spacing", None),
    "spacing-nan": ({"spacing": [float("nan"), 1, 1]}, "spacing", None),
    "min-island-inf": ({"min_island_mm3": float("inf")}, "min_island_mm3", {"islands": {"min_volume_mm3": 1e999}}),
    "min-island-nan": ({"min_island_mm3": float("nan")}, "min_island_mm3", {"islands": {"min_volume_mm3": 1e999 * 0}}),
    "iso-inf": ({"iso": float("inf")}, "iso", {"iso": {"iso": 1e999}}),
    "iso-beyond-float32": ({"iso": 1e300}, "iso", {"iso": {"iso": 1e300}}),
    "hu-offset-inf": ({"preset": "bone", "hu_offset": float("-inf")}, "hu_offset", {"iso": {"hu_offset": -1e999}}),
    "max-triangles-huge": ({"max_triangles": 10**30}, "max_triangles", {"decimate": {"max_triangles": 10**30}}),
    "keep-largest-huge": ({"keep_largest": 10**30}, "keep_largest", {"islands": {"keep_largest": 10**30}}),
    "angle-nan": ({"angle": float("nan")}, "angle", {"smooth": {"angle_deg": 1e999 * 0}}),
    "sigma-inf": (None, None, {"gaussian": {"sigma_voxels": 1e999}}),
    "threshold-nan": (None, None, {"preprocess": {"threshold": 1e999 * 0}}),
}


@pytest.mark.parametrize("kind", list(ABSURD))
def test_absurd_parameters_are_refused_by_the_api_and_the_engine(kind: str, client: TestClient) -> None:
    flat, field, engine = ABSURD[kind]
    if flat is not None:
        files = {"file": ("scan.zip", HEADSQ_ZIP.read_bytes(), "application/zip")}
        params = {"spacing": [1.5, 3.2, 3.2], **flat}
        resp = client.post("/v1/jobs", files=files, data={"params": json.dumps(params)}, headers=KEY)
        body = assert_problem(resp, 422)
        assert field in json.dumps(body.get("errors")), body
        with pytest.raises(ValueError):
            JobParams.model_validate(flat)
    if engine is not None:
        with pytest.raises(ValueError):
            ReconParams.from_dict(engine)
    _no_job_files(client)


def test_plausible_spacing_is_accepted() -> None:
    for spacing in ([1e-4, 1e-4, 1e-4], [100, 100, 100], [0.05, 0.05, 0.05]):
        JobParams.model_validate({"spacing": spacing})


# -- 4. unhandled errors: every request ends in a documented status with problem+json -----------------------------
def _deep_params(depth: int = 20_000) -> str:
    return '{"iso": ' + "[" * depth + "]" * depth + "}"


ODD_REQUESTS: dict[str, tuple[Callable[[TestClient], Any], int]] = {
    "params-nested-20000-deep": (
        lambda c: c.post(
            "/v1/jobs",
            files={"file": ("s.zip", HEADSQ_ZIP.read_bytes())},
            data={"params": _deep_params()},
            headers=KEY,
        ),
        422,
    ),
    "offset-24-digits": (lambda c: c.get("/v1/jobs", params={"offset": "1" * 24}, headers=KEY), 422),
    "limit-24-digits": (lambda c: c.get("/v1/jobs", params={"limit": "9" * 24}, headers=KEY), 422),
    "content-length-absurd": (
        lambda c: c.post("/v1/jobs", content=b"x", headers={**KEY, "Content-Length": "9" * 40}),
        (400, 413, 415),
    ),
    "unknown-path": (lambda c: c.get("/v1/nothing"), 404),
    "options-on-a-job": (lambda c: c.options("/v1/jobs/" + "0" * 32, headers=KEY), 405),
}


@pytest.mark.parametrize("kind", list(ODD_REQUESTS))
def test_odd_requests_end_in_a_problem(kind: str, client: TestClient) -> None:
    call, status = ODD_REQUESTS[kind]
    assert_problem(call(client), status)


def test_options_lists_every_method_of_the_path(client: TestClient) -> None:
    resp = client.options("/v1/jobs/" + "0" * 32, headers=KEY)
    assert_problem(resp, 405)
    assert {m.strip() for m in resp.headers["allow"].split(",")} >= {"GET", "DELETE"}, resp.headers
    allow = client.options("/v1/jobs").headers["allow"]
    assert {m.strip() for m in allow.split(",")} >= {"GET", "POST"}, allow


def test_unexpected_errors_are_problems_without_traceback(client: TestClient) -> None:
    app = client.app

    @app.get("/boom")  # type: ignore[attr-defined,untyped-decorator]
    def boom() -> None:
        raise RuntimeError("secret internals /etc/passwd")

    app.openapi_schema = None  # type: ignore[attr-defined]
    body = assert_problem(client.get("/boom"), 500)
    assert "secret" not in json.dumps(body) and "Traceback" not in json.dumps(body), body
    assert client.get("/healthz").status_code == 200


# -- 5. the contract: every error is declared as problem+json ------------------------------------------------------
def _operations() -> list[tuple[str, str, str, dict[str, Any]]]:
    from service.openapi import DEFAULT

    doc = json.loads(DEFAULT.read_text())
    return [
        (path, method, code, response)
        for path, ops in doc["paths"].items()
        for method, op in ops.items()
        for code, response in op["responses"].items()
    ]


@pytest.mark.parametrize(("path", "method", "code", "response"), _operations())
def test_errors_are_declared_as_problem_json(path: str, method: str, code: str, response: dict[str, Any]) -> None:
    if code.startswith(("4", "5")) and path != "/readyz":
        assert list(response.get("content", {})) == ["application/problem+json"], (path, method, code, response)


def test_docs_load_nothing_from_the_internet(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200
    import re

    sources = re.findall(r'(?:src|href)=["\']([^"\']+)', page.text)
    assert sources and not [s for s in sources if "//" in s], sources
    for src in sources:
        assert client.get(src).status_code == 200, src
    assert "http" not in "".join(re.findall(r"url: *'([^']*)'", page.text))


# -- 6. zip bomb within the ratio floor: refused at upload, members streamed ---------------------------------------
def test_bomb_of_small_members_is_refused_at_upload(client: TestClient, tmp_path: Path) -> None:
    data = bomb_of_small_members()
    path = tmp_path / "bomb.zip"
    path.write_bytes(data)
    with pytest.raises(InputError, match="zip bomb"):
        inspect_input(path)
    files = {"file": ("bomb.zip", data, "application/zip")}
    body = assert_problem(
        client.post("/v1/jobs", files=files, data={"params": json.dumps(HEADSQ_PARAMS)}, headers=KEY), 422
    )
    assert "bomb" in body["detail"], body
    _no_job_files(client)


def test_archive_members_are_read_one_at_a_time(tmp_path: Path) -> None:
    """Opening an archive holds no member in memory; reading them one by one holds one at a time."""
    path = tmp_path / "noise.zip"
    rng = np.random.default_rng(0)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for i in range(24):
            zf.writestr(f"s/{i:03d}.npy", rng.bytes(1 << 20))
    tracemalloc.start()
    try:
        with open_members(path) as members:
            opened = tracemalloc.get_traced_memory()[1]
            sizes = [len(m.read()) for m in members.members]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sizes == [1 << 20] * 24
    assert opened < 4 << 20, f"opening held {opened:,} bytes"
    assert peak < 8 << 20, f"reading one at a time peaked at {peak:,} bytes"


# -- 7. strict multipart -------------------------------------------------------------------------------------------
_ZIP = HEADSQ_ZIP.read_bytes()
_PARAMS = json.dumps(HEADSQ_PARAMS).encode()
BAD_BODIES = {
    "no-closing-boundary": _multipart([("file", "s.zip", _ZIP), ("params", None, b'{"iso": 1150')], close=False),
    "no-closing-boundary-after-file": _multipart([("params", None, _PARAMS), ("file", "s.zip", _ZIP)], close=False),
    "params-twice": _multipart([("file", "s.zip", _ZIP), ("params", None, _PARAMS), ("params", None, b"{}")]),
    "file-twice": _multipart([("file", "a.zip", _ZIP), ("file", "b.zip", _ZIP), ("params", None, _PARAMS)]),
    "cut-inside-headers": _multipart([("file", "s.zip", _ZIP)])[:40],
    "huge-part-header": _multipart([("file", "s" * 40_000 + ".zip", _ZIP), ("params", None, _PARAMS)]),
}


@pytest.mark.parametrize("kind", list(BAD_BODIES))
def test_malformed_multipart_is_400(kind: str, client: TestClient) -> None:
    body = assert_problem(_post_raw(client, BAD_BODIES[kind]), 400)
    assert len(body["detail"]) > 10
    _no_job_files(client)


def test_well_formed_multipart_is_accepted(client: TestClient) -> None:
    resp = _post_raw(client, _multipart([("file", "s.zip", _ZIP), ("params", None, _PARAMS)]))
    assert resp.status_code == 202, resp.text
    assert resp.json()["params"]["iso"] == 1150


# -- 8. one answer for every download token that does not verify ---------------------------------------------------
BAD_TOKENS = {
    "not-a-token": "not-a-token",
    "three-parts": "a.b.c",
    "empty": "",
    "slash": "abc/def",
    "dot-dot": "..%2F..%2Fetc",
    "non-ascii": "\u00e9t\u00e9.\u00e9t\u00e9",
    "percent-junk": "%ff%fe.%00",
    "very-long": "A" * 6000 + "." + "B" * 43,
    "signature-only": ".abc",
}


@pytest.mark.parametrize("kind", list(BAD_TOKENS))
def test_every_bad_token_is_403(kind: str, client: TestClient) -> None:
    assert_problem(client.get(f"/v1/files/{BAD_TOKENS[kind]}"), 403)


# -- 2. a full disk (the storage layer; the real thing runs in test_hardening_live) --------------------------------
def _sqlite_full() -> Exception:
    exc = sqlite3.OperationalError("database or disk is full")
    exc.sqlite_errorcode = sqlite3.SQLITE_FULL  # type: ignore[attr-defined]
    return OperationalError("INSERT", {}, exc)


STORAGE_ERRORS: dict[str, tuple[Callable[[], BaseException], bool]] = {
    "enospc": (lambda: OSError(errno.ENOSPC, "No space left on device"), True),
    "edquot": (lambda: OSError(errno.EDQUOT, "Disk quota exceeded"), True),
    "efbig": (lambda: OSError(errno.EFBIG, "File too large"), True),
    "sqlite-full": (_sqlite_full, True),
    "eacces": (lambda: PermissionError(errno.EACCES, "Permission denied"), False),
    "value-error": (lambda: ValueError("no"), False),
}


@pytest.mark.parametrize("kind", list(STORAGE_ERRORS))
def test_storage_full_is_recognised(kind: str) -> None:
    make, full = STORAGE_ERRORS[kind]
    assert is_storage_full(make()) is full
    try:
        raise RuntimeError("wrapped") from make()
    except RuntimeError as wrapped:
        assert is_storage_full(wrapped) is full


def test_staging_left_by_earlier_attempts_is_cleaned(tmp_path: Path) -> None:
    store = LocalStorage(tmp_path)
    job = "c" * 32
    w = store.upload_writer(job, 100)
    w.write(b"x")
    w.commit()
    left = [store.staging_dir(job), store.staging_dir(job), tmp_path / "jobs" / job / ".old-0123"]
    left.append(tmp_path / "jobs" / job / ".fetch-4567")  # a worker killed while fetching a DICOMweb series
    for folder in left[2:]:
        folder.mkdir()
    for folder in left:
        (folder / "model.stl").write_bytes(b"partial")
    assert store.clean_staging(job) == 4
    assert sorted(p.name for p in (tmp_path / "jobs" / job).iterdir()) == ["upload"]


# -- issue 13: an image stack without a voxel size is refused at upload --------------------------------------------
def _tiff_zip() -> bytes:
    import tifffile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for z, plane in enumerate(sphere_volume((8, 16, 16))):
            tiff = io.BytesIO()
            tifffile.imwrite(tiff, plane, resolution=(10.0, 10.0), resolutionunit="CENTIMETER")
            zf.writestr(f"s/{z:03d}.tif", tiff.getvalue())
    return buf.getvalue()


SPACING_AT_UPLOAD = {
    # name: (archive, params, accepted?)
    "png-without-spacing": (lambda: slice_zip(sphere_volume((8, 16, 16))), {"iso": 500}, False),
    "png-with-spacing": (lambda: slice_zip(sphere_volume((8, 16, 16))), {"iso": 500, "spacing": [1, 1, 1]}, True),
    "npy-without-spacing": (lambda: _npy_bytes(), {"iso": 500}, False),
    "tiff-without-spacing": (_tiff_zip, {"iso": 500}, True),  # its tags may carry the voxel size
    "one-png-without-spacing": (lambda: png_bytes(sphere_volume((1, 16, 16))[0]), {"iso": 500}, False),
}


def _npy_bytes() -> bytes:
    buf = io.BytesIO()
    np.save(buf, sphere_volume((8, 16, 16)))
    return buf.getvalue()


@pytest.mark.parametrize("kind", list(SPACING_AT_UPLOAD))
def test_stack_without_spacing_is_refused_at_upload(kind: str, client: TestClient) -> None:
    make, params, accepted = SPACING_AT_UPLOAD[kind]
    files = {"file": (f"{kind}.zip", make(), "application/octet-stream")}
    resp = client.post("/v1/jobs", files=files, data={"params": json.dumps(params)}, headers=KEY)
    if accepted:
        assert resp.status_code == 202, resp.text
    else:
        body = assert_problem(resp, (415, 422))
        assert "spacing" in body["detail"] or "single 2-D image" in body["detail"], body


@pytest.mark.parametrize(
    ("engine_says", "client_reads"),
    [
        ("upload holds no label map", "scan<1>.zip holds no label map"),
        ("expected PNG slices in upload, found none", "expected PNG slices in scan<1>.zip, found none"),
        ("cannot decode the pixels of upload/a.dcm (RLE)", "cannot decode the pixels of scan<1>.zip/a.dcm (RLE)"),
        ("the upload was cut, re-uploaded, an uploader", "the upload was cut, re-uploaded, an uploader"),
    ],
)
def test_an_engine_message_names_the_clients_file_wherever_it_names_the_upload(engine_says, client_reads) -> None:
    from core.logsafe import relabel

    assert relabel(engine_says, "scan<1>.zip") == client_reads
