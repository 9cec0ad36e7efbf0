"""POST /v1/jobs/{id}/orient through the real worker: a finished image-stack model is placed in another orientation
and every output re-published (no reconstruction); the report and the job's params record the new frame. And the
OpenAPI document lists /v1/webhook-secret once (under one tag: /docs showed it under two)."""

from __future__ import annotations

import json
from typing import Any

import httpx
import numpy as np

from engine.export.stl import from_stl
from tests.service.conftest import slice_zip, sphere_volume
from tests.service.procs import ServiceStack, submit, wait_for_job

TURN_OVER = {"first_slice": "inferior", "flip_lr": False, "flip_ap": True}


def _marked() -> np.ndarray:
    vol = sphere_volume((16, 24, 24), 0.3)
    vol[1:4, 10:14, 10:14] = 1000  # a bump toward the first slice (superior by default)
    return vol


def _files(anon: httpx.Client, job: dict[str, Any]) -> dict[str, bytes]:
    return {o["name"]: anon.get(o["url"]).content for o in job["outputs"]}


def test_orient_republishes_every_output_in_the_new_frame(
    stack: ServiceStack, client_a: httpx.Client, client_b: httpx.Client, anon: httpx.Client
) -> None:
    resp = submit(client_a, slice_zip(_marked()), {"iso": 500, "spacing": [1.0, 1.0, 1.0]})
    assert resp.status_code == 202, resp.text
    job_id = resp.json()["id"]
    assert client_a.post(f"/v1/jobs/{job_id}/orient", json=TURN_OVER).status_code in (409, 202)  # maybe not done
    job = wait_for_job(client_a, job_id, stack=stack, timeout=120)
    assert job["state"] == "succeeded", json.dumps(job)
    job = wait_for_job(client_a, job_id, stack=stack, timeout=60, until=lambda j: j["stage"] == "done")
    before = _files(anon, job)
    z_before = from_stl(before["model.stl"])[0][:, 0]
    assert client_b.post(f"/v1/jobs/{job_id}/orient", json=TURN_OVER).status_code == 404  # another key's job
    assert client_a.post(f"/v1/jobs/{job_id}/orient", json={"first_slice": "top"}).status_code == 422
    assert client_a.post(f"/v1/jobs/{job_id}/orient", json={"flip_xy": True}).status_code == 422

    resp = client_a.post(f"/v1/jobs/{job_id}/orient", json=TURN_OVER)
    assert resp.status_code == 202, resp.text
    assert resp.json()["state"] == "succeeded" and resp.json()["stage"] == "orienting"  # files stay downloadable
    job = wait_for_job(client_a, job_id, stack=stack, timeout=60, until=lambda j: j["stage"] == "done")
    assert job["state"] == "succeeded" and job["error"] is None, json.dumps(job)
    assert job["params"]["orient"] == TURN_OVER
    after = _files(anon, job)
    assert set(after) == set(before)
    assert all(after[name] != before[name] for name in after), "every output is re-published"
    report = json.loads(after["report.json"])
    assert report["parameters"]["orient"] == TURN_OVER
    assert np.diag(np.array(report["frame"]["patient_from_grid_xyz"])[:3, :3]).tolist() == [1.0, -1.0, 1.0]
    assert report["reoriented"]["from"]["first_slice"] == "superior"
    assert all(o["bytes"] == len(after[o["name"]]) for o in job["outputs"])
    # the bump (superior before) is now inferior: the print model turned over within the stack's box
    z_after = from_stl(after["model.stl"])[0][:, 0]
    extent = 15.0  # 16 slices of 1 mm: the stack's box keeps its place, from 0 to 15 mm
    assert z_before.max() - z_before.mean() > z_before.mean() - z_before.min()  # the bump on top (superior)
    np.testing.assert_allclose(
        [z_after.min(), z_after.max()], [extent - z_before.max(), extent - z_before.min()], atol=1e-4
    )


def test_orient_is_refused_unless_succeeded(stack: ServiceStack, client_a: httpx.Client) -> None:
    resp = submit(client_a, slice_zip(sphere_volume()), {"iso": 50000, "spacing": [1, 1, 1]})  # no surface: fails
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=60)
    assert job["state"] == "failed"
    assert client_a.post(f"/v1/jobs/{job['id']}/orient", json=TURN_OVER).status_code == 409


def test_docs_list_the_webhook_secret_once(client_a: httpx.Client) -> None:
    schema = client_a.get("/openapi.json").json()
    operation = schema["paths"]["/v1/webhook-secret"]["get"]
    assert operation["tags"] == ["webhooks"]  # one tag: Swagger UI lists an operation under each of its tags
    listed = [(p, m) for p, ops in schema["paths"].items() for m in ops if p.endswith("webhook-secret")]
    assert listed == [("/v1/webhook-secret", "get")]
    assert "/v1/jobs/{job_id}/orient" in schema["paths"]
