"""An OME-Zarr upload's level by name (issue 46: ``zarr_level``, the API's form of the CLI's ``--zarr-level``): a
real API and worker read the level asked for; a malformed level is a 422 naming the field, and a level the image
lacks fails the job with the levels it has."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from tests.engine.omezarr_factory import zip_folder
from tests.service.checks import assert_succeeded
from tests.service.conftest import app_client
from tests.service.procs import ServiceStack, submit, wait_for_job

pytest.importorskip("zarr")

FIXTURE = Path(__file__).resolve().parents[1] / "data" / "ome_zarr" / "phantom_v05.ome.zarr"  # ome-zarr-py's
KEY = {"X-API-Key": "key-a"}


@pytest.mark.parametrize("bad", ["../0", -1, True, "a b"])
def test_a_malformed_level_is_a_422_naming_it(tmp_path: Path, bad: object) -> None:
    body = zip_folder(FIXTURE, tmp_path / "scan.zip").read_bytes()
    with app_client(tmp_path / "data") as client:
        resp = client.post("/v1/jobs", files={"file": ("scan.zip", body, "application/zip")},
                           data={"params": json.dumps({"zarr_level": bad})}, headers=KEY)  # fmt: skip
        assert resp.status_code == 422, resp.text
        assert "zarr_level" in resp.text


def test_the_worker_reads_the_level_asked_for(
    stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client, tmp_path: Path
) -> None:
    body = zip_folder(FIXTURE, tmp_path / "scan.zip").read_bytes()
    resp = submit(client_a, body, {"iso": 1100, "zarr_level": "s1"}, filename="scan.zip")
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=300)
    files = assert_succeeded(job, stack.base_url)
    report = anon.get(files["report.json"]["url"]).json()
    assert report["input"]["source"]["level"] == "s1" and report["input"]["shape_zyx"] == [8, 16, 20]
    resp = submit(client_a, body, {"iso": 1100, "zarr_level": "s5"}, filename="scan.zip")
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=300)
    assert job["state"] == "failed" and job["error"]["code"] == "bad_input", job
    assert "no level 's5'; its levels are 0: 's0' (16x32x40), 1: 's1' (8x16x20)" in job["error"]["message"]
