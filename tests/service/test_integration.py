"""The issue's "Done when": a real redis-server, a real ``bonemesh worker`` and a real ``bonemesh serve``; upload a
real scan over HTTP, poll to success, download every output through its signed link without the API key, and check
it (STL watertight and in mm, phone GLB Draco-decodable within its triangle budget, report.json)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import trimesh

from tests.service.checks import assert_mesh_in_scan_mm, assert_succeeded, check_outputs
from tests.service.conftest import (
    HEADSQ,
    SYNTHETIC_DICOM_ORIGIN_LPS,
    Scan,
    shared_scan,
    synthetic_dicom_scan,
    zip_to_tar_gz,
)
from tests.service.procs import ServiceStack, submit, wait_for_job


def _scan(name: str, folder: Path) -> Scan:
    if name == "headsq":
        return HEADSQ
    if name == "synthetic_dicom":
        return synthetic_dicom_scan(folder)
    scan = shared_scan(name)
    if scan is None:
        pytest.skip(f"{name} is absent: the ../shared/data checkout is not beside the repo")
    return scan


@pytest.mark.parametrize("name", ["headsq", "cranium", "head_phantom_dicom", "synthetic_dicom"])
def test_upload_poll_download(
    name: str, stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client, tmp_path: Path
) -> None:
    scan = _scan(name, tmp_path)
    resp = submit(client_a, scan.path, scan.params)
    assert resp.status_code == 202, resp.text
    job = resp.json()
    assert resp.headers["location"].endswith(f"/v1/jobs/{job['id']}"), resp.headers
    assert job["state"] in ("queued", "running"), job
    assert job["outputs"] in (None, []), job
    for key, value in scan.params.items():
        assert job["params"][key] == value, (key, job["params"])

    job = wait_for_job(client_a, job["id"], stack=stack, timeout=300)
    outputs = assert_succeeded(job, stack.base_url)
    assert job["attempts"] == 1, job
    report = check_outputs(anon, outputs, scan.shape_zyx, scan.spacing_zyx_mm)
    assert report["device"]["name"] == "cpu", report["device"]
    if name == "synthetic_dicom":  # the STL lies at the series' patient position, not at the grid's origin
        assert report["frame"]["placed_by"].startswith("DICOM"), report["frame"]
        offset = [row[3] for row in report["frame"]["patient_from_grid_xyz"][:3]]
        np.testing.assert_allclose(offset, SYNTHETIC_DICOM_ORIGIN_LPS, atol=1e-3)

    listed = client_a.get("/v1/jobs", params={"limit": 200}).json()
    assert job["id"] in [j["id"] for j in listed["items"]]


def test_the_box_check_follows_the_report_frame() -> None:
    """A box filling the grid, placed by an oblique frame far from the origin, passes only with that frame."""
    shape, spacing = (11, 21, 31), (1.0, 0.5, 0.5)
    box = trimesh.creation.box(extents=[15.0, 10.0, 10.0])
    box.apply_translation([7.5, 5.0, 5.0])  # grid (x, y, z) mm: 0..15, 0..10, 0..10
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = [[c, -s, 0], [s, c, 0], [0, 0, -1]], [-120.0, -90.0, -600.0]
    frame = {"patient_from_grid_xyz": m.tolist()}
    placed = box.copy().apply_transform(m)
    assert_mesh_in_scan_mm(placed, shape, spacing, frame)
    with pytest.raises(AssertionError, match="outside the scan's extent"):
        assert_mesh_in_scan_mm(placed, shape, spacing)  # the old check: the grid box at the origin
    with pytest.raises(AssertionError, match="outside the scan's extent"):
        assert_mesh_in_scan_mm(box, shape, spacing, frame)  # an STL left in grid coordinates


def test_tar_gz_upload(stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client) -> None:
    """The same slices as a tar.gz give the same model."""
    resp = submit(client_a, zip_to_tar_gz(HEADSQ.path), HEADSQ.params, filename="headsq.tar.gz")
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=300)
    outputs = assert_succeeded(job, stack.base_url)
    check_outputs(anon, outputs, HEADSQ.shape_zyx, HEADSQ.spacing_zyx_mm)
    # the API's own info lines reach its log (`bonemesh serve`'s logging), the upload's name never
    logs = "".join(p.read_text(errors="replace") for p in stack.log_dir.glob("server-*.log"))
    assert f"job {job['id']}: upload of " in logs and f"job {job['id']} upload timings {{" in logs
    assert "headsq.tar.gz" not in logs


def test_health(anon: httpx.Client) -> None:
    resp = anon.get("/healthz")
    assert resp.status_code == 200 and resp.json() == {"status": "ok"}
    resp = anon.get("/readyz")
    assert resp.status_code == 200, resp.text
    body: dict[str, Any] = resp.json()
    assert "redis" in str(body) and "database" in str(body) and "storage" in str(body), body
