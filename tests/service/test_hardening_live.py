"""What the attack suite of issue 15 found, against real processes: forged log lines through the worker, a full data
volume (a real tmpfs), staging folders of a killed attempt, DICOM series with NaN positions or mixed series, and
schemathesis fuzzing the running API against ``openapi/openapi.json``."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import warnings
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.service.checks import assert_problem, assert_succeeded
from tests.service.conftest import HEADSQ, StackFactory
from tests.service.procs import REPO, ServiceStack, submit, wait_for_job

FORGED = "FORGED bonemesh.worker: job 0 succeeded"


def _dicom_zip(series_specs: list[dict[str, Any]], rename: dict[int, str] | None = None) -> bytes:
    """A zip of synthetic CT/MR series: a 1500 HU ball in -1000 HU air. Each spec: positions_mm, modality,
    description, and optionally nan_at (a slice whose ImagePositionPatient becomes NaN)."""
    import pydicom
    from pydicom.uid import generate_uid

    from tests.engine.dicom_factory import series

    def ball(p: np.ndarray) -> np.ndarray:
        return np.where(np.linalg.norm(p - np.array([0.0, 0.0, 4.0]), axis=-1) < 3.5, 1500.0, -1000.0)

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, spec in enumerate(series_specs):
            files = series(
                ball,
                positions_mm=spec["positions_mm"],
                series_uid=generate_uid(),
                name=f"S{k}_",
                modality=spec.get("modality", "CT"),
                description=spec.get("description", f"series {k}"),
            )
            for i, (name, data) in enumerate(files.items()):
                if spec.get("nan_at") == i:
                    ds = pydicom.dcmread(io.BytesIO(data))
                    with warnings.catch_warnings():  # pydicom rightly warns that 'nan' is no valid DS
                        warnings.simplefilter("ignore")
                        ds.ImagePositionPatient = ["nan", "0", str(i)]
                        out = io.BytesIO()
                        ds.save_as(out)
                    data = out.getvalue()
                zf.writestr((rename or {}).get(i, f"DICOM/{name}"), data)
    return buf.getvalue()


def _post_named(client: httpx.Client, data: bytes, filename: str, params: dict[str, Any]) -> httpx.Response:
    """A multipart POST written by hand, so the file name carries raw control characters (a lone LF)."""
    boundary = "f0rged"
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{filename}"\r\n\r\n'.encode()
        + data
        + f'\r\n--{boundary}\r\nContent-Disposition: form-data; name="params"\r\n\r\n{json.dumps(params)}'.encode()
        + f"\r\n--{boundary}--\r\n".encode()
    )
    return client.post("/v1/jobs", content=body, headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})


# -- 1. log forging through the worker ----------------------------------------------------------------------------
def test_client_names_never_forge_a_log_line(stack: ServiceStack, client_a: httpx.Client) -> None:
    """A DICOM series that fails in the worker (two slices at one position), uploaded under a name with a newline
    and with member names that hold newlines: no log line may start with the client's text."""
    rename = {0: f"DICOM/a\n{FORGED}\n", 1: f"DICOM/b\r\n{FORGED}\u2028"}
    data = _dicom_zip([{"positions_mm": [0, 1, 1, 2, 3, 4, 5, 6]}], rename=rename)
    resp = _post_named(client_a, data, f"scan\n{FORGED}.zip", {"preset": "bone"})
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=120)
    assert job["state"] == "failed" and job["error"]["code"] == "bad_input", job
    assert "\n" not in job["error"]["message"] and "\n" not in job["upload_name"], job
    lines = [line for log in stack.log_dir.glob("*.log") for line in log.read_text(errors="replace").splitlines()]
    assert any(job["id"] in line for line in lines), "the worker logged nothing about the job"
    forged = [line for line in lines if line.lstrip().startswith("FORGED")]
    assert not forged, forged


# -- 11. DICOM: NaN geometry refused; a mixed upload uses the largest CT series and says so -----------------------
def test_nan_position_fails_the_job_with_a_reason(stack: ServiceStack, client_a: httpx.Client) -> None:
    data = _dicom_zip([{"positions_mm": list(range(8)), "nan_at": 3}])
    resp = submit(client_a, data, {"preset": "bone"}, filename="nan.zip")
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=120)
    assert job["state"] == "failed" and job["error"]["code"] == "bad_input", job
    assert "NaN" in job["error"]["message"] and "ImagePositionPatient" in job["error"]["message"], job


def test_mixed_series_use_the_largest_ct_and_the_report_says_so(
    stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client
) -> None:
    data = _dicom_zip(
        [
            {"positions_mm": list(range(9)), "description": "bone CT"},
            {"positions_mm": [0, 2, 4, 6, 8], "description": "scout CT"},
            {"positions_mm": [0.5 * k for k in range(14)], "modality": "MR", "description": "T1 MR"},
        ]
    )
    # the ball lies in air, with no body around it: the body mask (on by default) would refuse the scan
    resp = submit(client_a, data, {"preset": "bone", "body": None}, filename="mixed.zip")
    assert resp.status_code == 202, resp.text
    assert resp.json()["params"]["body"] is None, resp.json()["params"]
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=180)
    outputs = assert_succeeded(job, stack.base_url)
    report = anon.get(outputs["report.json"]["url"]).json()
    choice = report["input"]["source"]["series"]
    # series are named by UID, number, modality and count: never by their free-text description (PHI)
    assert choice["used"]["modality"] == "CT" and choice["used"]["images"] == 9, choice
    assert sorted((s["modality"], s["images"]) for s in choice["ignored"]) == [("CT", 5), ("MR", 14)], choice
    assert "description" not in json.dumps(choice) and "bone CT" not in json.dumps(report), choice
    assert report["input"]["shape_zyx"][0] == 9
    assert "body_mask" not in report, report["body_mask"]  # "body": null reached the worker: no mask ran


# -- 9. staging folders of a killed attempt are removed by the attempt that completes -----------------------------
def test_completing_attempt_removes_earlier_staging(make_stack: StackFactory) -> None:
    _, stack = make_stack(workers=0)
    with stack.client("key-a") as client:
        job_id = submit(client, HEADSQ.path, HEADSQ.params).json()["id"]
        folder = stack.data_dir / "jobs" / job_id
        for name in (".staging-0123456789abcdef", ".staging-fedcba9876543210/.bonemesh-x", ".old-00aa"):
            (folder / name).mkdir(parents=True)
            (folder / name / "model.stl").write_bytes(b"left by a killed worker")
        stack.start_worker()
        job = wait_for_job(client, job_id, stack=stack, timeout=300)
        assert_succeeded(job, stack.base_url)
        assert sorted(p.name for p in folder.iterdir()) == ["outputs", "upload"]


# -- 2. a full data volume: 507 with nothing kept, the service answering; the worker fails the job with a reason ---
@contextlib.contextmanager
def _tmpfs(path: Path, megabytes: int) -> Iterator[None]:
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a small tmpfs (a real full disk) needs root")
    path.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={megabytes}m", "tmpfs", str(path)], capture_output=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {res.stderr.decode(errors='replace').strip()}")
    try:
        yield
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True, check=False)


def _fill(path: Path, leave_bytes: int) -> Path:
    """A filler file that leaves about ``leave_bytes`` free on the file system of ``path``."""
    filler = path / "filler.bin"
    with filler.open("wb") as fh:
        chunk = bytes(1 << 20)
        while (free := shutil.disk_usage(path).free) > leave_bytes:
            fh.write(chunk[: min(len(chunk), free - leave_bytes)])
            fh.flush()
    return filler


def test_full_disk_is_507_and_a_failed_job_with_a_reason(make_stack: StackFactory) -> None:
    _, stack = make_stack(server=False, workers=0)
    with _tmpfs(stack.data_dir, 24):
        stack.start_server()
        with stack.client("key-a") as client:

            def stream() -> Iterator[bytes]:  # no Content-Length: the disk fills while the upload streams
                yield b'--b0nemesh\r\nContent-Disposition: form-data; name="file"; filename="big.zip"\r\n\r\n'
                for _ in range(40):
                    yield os.urandom(1 << 20)
                yield b"\r\n--b0nemesh--\r\n"

            headers = {"Content-Type": "multipart/form-data; boundary=b0nemesh"}
            body = assert_problem(client.post("/v1/jobs", content=stream(), headers=headers), 507)
            assert "full" in body["detail"], body
            declared = submit(client, os.urandom(40 << 20), HEADSQ.params, filename="big.zip")
            assert_problem(declared, 507)  # refused on its Content-Length
            jobs = stack.data_dir / "jobs"
            assert not [p for p in jobs.rglob("*") if p.is_file()], "the partial upload was kept"
            assert client.get("/v1/jobs").json()["total"] == 0

            # the service keeps answering: a scan that fits is accepted...
            accepted = submit(client, HEADSQ.path, HEADSQ.params)
            assert accepted.status_code == 202, accepted.text
            job_id = accepted.json()["id"]
            # ...but then the disk fills before the worker writes the models
            filler = _fill(stack.data_dir, 256 << 10)
            stack.start_worker()
            job = wait_for_job(client, job_id, stack=stack, timeout=300)
            assert job["state"] == "failed" and job["error"]["code"] == "storage_full", job
            assert "full" in job["error"]["message"] and job["outputs"] is None, job
            left = sorted(p.name for p in (jobs / job_id).iterdir())
            assert left == ["upload"], f"a failed job published or left: {left}"

            filler.unlink()  # space again: the same worker builds the next job
            again = submit(client, HEADSQ.path, HEADSQ.params).json()["id"]
            assert_succeeded(wait_for_job(client, again, stack=stack, timeout=300), stack.base_url)
        stack.close()


# -- 5. the contract: schemathesis against the running API --------------------------------------------------------
@pytest.mark.fuzz
def test_schemathesis_finds_nothing(make_stack: StackFactory, tmp_path: Path) -> None:
    """Every check, bounded examples and time; the one check left out is "schema-valid data accepted": random
    bytes are schema-valid as a 'file' but are rightly refused as a scan (415/422)."""
    _, stack = make_stack(workers=0)
    cli = Path(sys.executable).parent / "schemathesis"
    argv = (
        [str(cli)]
        if cli.exists()
        else [sys.executable, "-c", "from schemathesis.cli import schemathesis; schemathesis()", "--"]
    )
    argv += [
        "run",
        str(REPO / "openapi" / "openapi.json"),
        "--url",
        stack.base_url,
        "--header",
        "X-API-Key: key-a",
        "--checks",
        "all",
        "--exclude-checks",
        "positive_data_acceptance",
        "--max-examples",
        "10",
        "--max-time",
        "75",
        "--seed",
        "15",
        "--workers",
        "1",
        "--no-color",
        "--report",
        "junit",
        "--report-dir",
        str(tmp_path),
    ]
    res = subprocess.run(argv, capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert res.returncode == 0, f"schemathesis found problems:\n{res.stdout[-12000:]}\n{res.stderr[-2000:]}"
    stack.check_alive()
