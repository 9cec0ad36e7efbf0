"""A DICOMweb fetch is complete or fails (issue 25), against the real Orthanc of ``tests.service.pacs_env`` and a
real HTTP gateway in front of it (``tests.service.dicomweb_gate``) that misbehaves as servers do: a series whose
files mix Explicit and Implicit VR Little Endian, Deflated, RLE and JPEG 2000 Lossless (plus a non-image instance)
is pulled whole by a job and its model delivered; a series the server cannot send whole fails the job
``source_incomplete`` with the counts, and nothing is delivered; a cut answer, repeated parts, a capped QIDO-RS,
failing QIDO-RS requests and a server refusing ``transfer-syntax=*`` are each met by ``fetch_series``.
"""

from __future__ import annotations

import io
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import (
    DeflatedExplicitVRLittleEndian,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    JPEG2000Lossless,
    RLELossless,
    generate_uid,
)

from core.pacs.config import DicomwebServer
from core.pacs.dicomweb import DicomwebError, fetch_series, list_instances
from core.pacs.multipart import MultipartError, split_multipart
from tests.engine.dicom_factory import PATIENT
from tests.service.dicomweb_gate import DicomwebGate
from tests.service.pacs_env import (
    Pacs,
    check_model_in_orthanc,
    download,
    generated_series,
    wait_delivered,
)
from tests.service.procs import wait_for_job

pytest.importorskip("dicomweb_client", reason="DICOMweb needs dicomweb-client (pip install 'bonemesh[pacs]')")
pytest.importorskip("pynetdicom", reason="the PACS tests need pynetdicom (pip install 'bonemesh[pacs]')")

SYNTAXES = (ExplicitVRLittleEndian, ImplicitVRLittleEndian, DeflatedExplicitVRLittleEndian, RLELossless)
SYNTAXES += (JPEG2000Lossless,)
RAW_DATA_STORAGE = "1.2.840.10008.5.1.4.1.1.66"
FAST = {"attempts": 3, "backoff_seconds": 0.01}


@pytest.fixture(scope="module")
def client(pacs_client: httpx.Client) -> httpx.Client:
    return pacs_client


@pytest.fixture
def gate(pacs: Pacs) -> Iterator[DicomwebGate]:
    pacs.gate.reset()
    yield pacs.gate
    pacs.gate.reset()


def mixed_series() -> tuple[list[bytes], str, str]:
    """The generated series (24 images of 36 x 36), image k in ``SYNTAXES[k % 5]``, plus one non-image instance
    of the series; files, study, series."""
    files, study, series_uid = generated_series()
    out = []
    for k, data in enumerate(files):
        ds = pydicom.dcmread(io.BytesIO(data))
        if SYNTAXES[k % len(SYNTAXES)] in (RLELossless, JPEG2000Lossless):
            ds.compress(SYNTAXES[k % len(SYNTAXES)])
        else:
            ds.file_meta.TransferSyntaxUID = SYNTAXES[k % len(SYNTAXES)]
        out.append(_bytes(ds))
    raw = Dataset()  # as a scanner's raw data or a dose record may sit in the series
    for key, value in PATIENT.items():
        setattr(raw, key, value)
    raw.SOPClassUID, raw.SOPInstanceUID = RAW_DATA_STORAGE, generate_uid()
    raw.StudyInstanceUID, raw.SeriesInstanceUID, raw.Modality = study, series_uid, "CT"
    raw.file_meta = meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = RAW_DATA_STORAGE, raw.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    return [*out, _bytes(raw)], study, series_uid


def _bytes(ds: Dataset) -> bytes:
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()


def store_in_orthanc(pacs: Pacs, files: list[bytes]) -> None:
    """Store the files with Orthanc's REST API, as they are (each in its own transfer syntax)."""
    for data in files:
        resp = httpx.post(f"{pacs.orthanc.url}/instances", content=data, timeout=30)
        resp.raise_for_status()
        assert resp.json()["Status"] == "Success", resp.text


def uid_of(data: bytes) -> str:
    return str(pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True).SOPInstanceUID)


def post_job(client: httpx.Client, server: str, study: str, series_uid: str) -> dict[str, Any]:
    source = {"dicomweb": {"server": server, "study_uid": study, "series_uid": series_uid}}
    resp = client.post("/v1/jobs", json={"source": source, "params": {"preset": "bone"}})
    assert resp.status_code == 202, resp.text
    return resp.json()


def check_files(folder: Path, files: list[bytes], *, as_stored: bool = True) -> None:
    """``folder`` holds each instance once, readable, with the same pixels (``as_stored``: in the syntax stored)."""
    want = {uid_of(f): pydicom.dcmread(io.BytesIO(f)) for f in files}
    got = {str(ds.SOPInstanceUID): ds for ds in (pydicom.dcmread(p) for p in sorted(folder.iterdir()))}
    assert sorted(got) == sorted(want)
    for uid, ds in got.items():
        assert not as_stored or ds.file_meta.TransferSyntaxUID == want[uid].file_meta.TransferSyntaxUID
        if "PixelData" in want[uid]:
            np.testing.assert_array_equal(ds.pixel_array, want[uid].pixel_array)


# -- through a job ----------------------------------------------------------------------------------------------
def test_a_series_in_mixed_transfer_syntaxes_is_pulled_whole(pacs: Pacs, client: httpx.Client) -> None:
    from dicomweb_client.api import DICOMwebClient

    files, study, series_uid = mixed_series()
    store_in_orthanc(pacs, files)
    # what issue 25 met: asked with dicomweb-client's default Accept (Explicit VR Little Endian), this Orthanc cannot
    # transcode JPEG 2000 and cuts the series answer short while answering 200
    old = sum(1 for _ in DICOMwebClient(pacs.orthanc.dicomweb_url).iter_series(study, series_uid))
    assert old < len(files)

    job = wait_delivered(pacs, client, post_job(client, "orthanc", study, series_uid)["id"])
    report = json.loads(download(job, "report.json"))
    source = report["input"]["source"]
    assert report["input"]["shape_zyx"][0] == source["files"] == len(files) - 1, source
    assert source["other_files_skipped"] == 1  # the non-image instance, retrieved and skipped by the loader
    check_model_in_orthanc(pacs, job, study)
    n = len(files)
    assert f"job {job['id']}: {n} of {n} instances retrieved with WADO-RS from orthanc" in pacs.logs_text()


def test_a_series_the_server_cannot_send_whole_fails_and_nothing_is_delivered(
    pacs: Pacs, client: httpx.Client, gate: DicomwebGate
) -> None:
    files, study, series_uid = mixed_series()
    store_in_orthanc(pacs, files)
    j2k = {uid_of(f) for f in files if pydicom.dcmread(io.BytesIO(f)).file_meta.TransferSyntaxUID == JPEG2000Lossless}
    gate.default_accept = True  # Orthanc is asked for Explicit VR Little Endian whatever the worker asks for

    job = post_job(client, "gate", study, series_uid)
    job = wait_for_job(client, job["id"], stack=pacs.stack, timeout=180)
    assert job["state"] == "failed" and job["error"]["code"] == "source_incomplete", json.dumps(job)
    message = job["error"]["message"]
    counts = re.search(r"server 'gate' returned (\d+) of (\d+) instances of the series \(missing: (\d+)\)", message)
    assert counts is not None, message
    assert tuple(map(int, counts.groups())) == (len(files) - len(j2k), len(files), len(j2k))
    assert "nothing was reconstructed or delivered" in message
    shown = re.findall(r"\d+(?:\.\d+){3,}", message.split("Missing SOP Instance UIDs:")[1])
    assert shown and set(shown) <= j2k
    assert {k for k, _ in gate.seen} >= {"qido", "series", "instance"}  # listed, asked whole, then one by one

    assert not job["outputs"]
    assert job["delivery"]["state"] == "skipped" and job["delivery"]["attempts"] == 0, json.dumps(job)
    assert pacs.orthanc.instances_of(study, "M3D") == []  # nothing stored into the patient's study
    job_dir = pacs.stack.data_dir / "jobs" / job["id"]
    assert not (job_dir / "upload").exists() and not list(job_dir.glob(".fetch-*"))  # no partial series kept
    logs = pacs.logs_text()
    assert f"job {job['id']}: {len(files) - len(j2k)} of {len(files)} instances retrieved" in logs
    assert not any(uid in logs for uid in j2k)  # counts in the logs, never the UIDs


# -- fetch_series against the gateway ---------------------------------------------------------------------------
def test_a_cut_answer_repeated_parts_and_a_capped_qido_still_bring_every_instance(
    pacs: Pacs, gate: DicomwebGate, tmp_path: Path
) -> None:
    files, study, series_uid = mixed_series()
    store_in_orthanc(pacs, files)
    server = DicomwebServer(url=gate.url, **FAST)
    n = len(files)

    gate.cut_series_after, gate.qido_cap = 5, 4  # 5 parts and half of the 6th, then the connection closes
    got = fetch_series(server, study, series_uid, tmp_path / "cut")
    assert (got.expected, got.retrieved, got.missing, got.one_by_one) == (n, n, (), n - 5)
    assert set(got.transfer_syntaxes) == set(SYNTAXES) and sum(got.transfer_syntaxes.values()) == n
    assert sum(1 for kind, _ in gate.seen if kind == "qido") == math.ceil(n / 4) + 1  # every page, then an empty one
    check_files(tmp_path / "cut", files)

    gate.reset()
    gate.repeat_parts = True  # every instance twice in the series answer
    got = fetch_series(server, study, series_uid, tmp_path / "twice")
    assert (got.retrieved, got.duplicates, got.one_by_one) == (n, n, 0)
    check_files(tmp_path / "twice", files)


def test_qido_is_retried_and_a_series_the_server_does_not_list_fails(
    pacs: Pacs, gate: DicomwebGate, tmp_path: Path
) -> None:
    files, study, series_uid = generated_series()
    store_in_orthanc(pacs, files[:12])
    server = DicomwebServer(url=gate.url, **FAST)

    gate.qido_failures = 2  # 503 twice, then answered
    assert fetch_series(server, study, series_uid, tmp_path / "a").retrieved == 12
    gate.qido_failures = 100
    with pytest.raises(DicomwebError, match=r"^QIDO-RS search of the series' instances: HTTP 503 after 3 attempts$"):
        fetch_series(server, study, series_uid, tmp_path / "b")
    gate.reset()
    with pytest.raises(DicomwebError, match="the server lists no instance of the series"):
        fetch_series(server, study, generate_uid(), tmp_path / "c")
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()
    down = DicomwebServer(url="http://127.0.0.1:9/dicom-web", **FAST)
    with pytest.raises(DicomwebError, match=r"no connection \(ConnectionError\) after 3 attempts") as err:
        fetch_series(down, study, series_uid, tmp_path / "d")
    assert "127.0.0.1" not in str(err.value) and "/dicom-web" not in str(err.value)  # no server path in errors


def test_a_server_refusing_any_transfer_syntax_is_asked_for_those_decodable_here(
    pacs: Pacs, gate: DicomwebGate, tmp_path: Path
) -> None:
    files, study, series_uid = mixed_series()
    store_in_orthanc(pacs, files)
    j2k = {uid_of(f) for f in files if pydicom.dcmread(io.BytesIO(f)).file_meta.TransferSyntaxUID == JPEG2000Lossless}
    gate.refuse_any = True  # 406 for transfer-syntax=*
    got = fetch_series(DicomwebServer(url=gate.url, **FAST), study, series_uid, tmp_path / "list")
    assert (got.expected, got.retrieved) == (len(files), len(files))
    accepts = [accept for kind, accept in gate.seen if kind in ("series", "instance")]
    assert "transfer-syntax=*" in accepts[0] and "transfer-syntax=1.2.840.10008.1.2.4.90," in accepts[1]
    # Orthanc reads the last syntax of a list and cannot transcode JPEG 2000: asked for JPEG 2000 alone, it sends
    # those instances as stored
    assert any(accept.endswith(f"; transfer-syntax={JPEG2000Lossless}") for accept in accepts)
    check_files(tmp_path / "list", files, as_stored=False)  # lossless whatever the syntax: the same pixels
    kept = {
        str(ds.SOPInstanceUID): ds.file_meta.TransferSyntaxUID
        for ds in map(pydicom.dcmread, (tmp_path / "list").iterdir())
    }
    assert {uid for uid, ts in kept.items() if ts == JPEG2000Lossless} == j2k


# -- the framing and the paging, by themselves ------------------------------------------------------------------
def _multipart(contents: list[bytes], boundary: bytes = b"b0und") -> bytes:
    head = b"\r\nContent-Type: application/dicom\r\n\r\n"
    return b"preamble" + b"".join(b"\r\n--" + boundary + head + c for c in contents) + b"\r\n--" + boundary + b"--\r\n"


def _chunks(data: bytes, size: int = 7) -> list[bytes]:
    return [data[i : i + size] for i in range(0, len(data), size)]


def test_split_multipart_gives_whole_parts_only() -> None:
    contents = [b"first\r\n--b0un", b"", b"third" * 50]
    body = _multipart(contents)
    assert list(split_multipart(_chunks(body), b"b0und")) == contents  # boundaries across chunks
    got: list[bytes] = []
    with pytest.raises(MultipartError, match="ended before its closing boundary") as err:
        got.extend(split_multipart(_chunks(body[: body.index(b"third") + 20]), b"b0und"))
    assert err.value.cut and got == contents[:2]  # the cut third part is not given out
    with pytest.raises(MultipartError, match="ended before") as err:  # the last part whole, no closing boundary
        list(split_multipart([body[: body.rindex(b"\r\n--b0und--")]], b"b0und"))
    with pytest.raises(MultipartError, match="Content-Length") as err:
        list(split_multipart([body.replace(b"Content-Type: application/dicom", b"Content-Length: 3")], b"b0und"))
    assert err.value.cut
    with pytest.raises(MultipartError, match="'text/html'") as err:
        list(split_multipart([body.replace(b"application/dicom", b"text/html")], b"b0und"))
    assert not err.value.cut


def test_list_instances_pages_through_caps_and_repeats() -> None:
    uids = [f"1.2.3.{k}" for k in range(10)]

    def server(cap: int, honours_offset: bool = True) -> Any:
        def page(params: dict[str, int]) -> list[Any]:
            start = params["offset"] if honours_offset else 0
            return [{"00080018": {"vr": "UI", "Value": [u]}} for u in uids[start : start + min(cap, params["limit"])]]

        return page

    assert list_instances(server(3), page=500) == uids  # a server capping at 3 a page
    assert list_instances(server(500), page=4) == uids
    assert list_instances(server(500, honours_offset=False), page=500) == uids  # the same page again: the end
    assert list_instances(server(3, honours_offset=False), page=500) == uids[:3]  # all such a server gives
    with pytest.raises(DicomwebError, match="lacks the instances' SOP Instance UIDs"):
        list_instances(lambda params: [{"00080016": {}}] if not params["offset"] else [])
