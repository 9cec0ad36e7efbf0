"""S3 storage end to end with real processes: a redis-server, two ``bonemesh serve`` (one handing out the store's
presigned links, one the API's signed links) and a ``bonemesh worker`` with a data folder of its own (no disk
shared with the API), all on a real S3 store (SeaweedFS). The bundled headsq scan runs; every output downloads
from the store, checked as the local-disk integration test checks it; no file of the job is on either local disk;
deleting the job deletes its objects."""

from __future__ import annotations

from pathlib import Path

import httpx

from tests.service.checks import check_outputs
from tests.service.conftest import HEADSQ, StackFactory
from tests.service.procs import submit, wait_for_job
from tests.service.seaweed import SeaweedServer


def test_a_job_runs_on_s3_and_every_output_downloads_from_the_store(
    make_stack: StackFactory, seaweed_server: SeaweedServer, tmp_path: Path
) -> None:
    bucket = seaweed_server.make_bucket()
    env = {**seaweed_server.env(bucket, "live"), "BONEMESH_DOWNLOAD_LINKS": "store"}
    _, stack = make_stack(server=False, workers=0, extra_env=env)
    stack.start_server()
    api_links = stack.start_server(extra_env={"BONEMESH_DOWNLOAD_LINKS": "api"})
    worker_data = tmp_path / "worker-data"
    stack.start_worker(extra_env={"BONEMESH_DATA_DIR": str(worker_data)})

    with stack.client() as client, httpx.Client(timeout=60) as anon:
        resp = submit(client, HEADSQ.path, HEADSQ.params)
        assert resp.status_code == 202, resp.text
        job = wait_for_job(client, resp.json()["id"], stack=stack, timeout=300)
        assert job["state"] == "succeeded", job
        outputs = {o["name"]: o for o in job["outputs"]}
        for out in outputs.values():  # the store's own presigned URLs
            assert out["url"].startswith(f"{seaweed_server.endpoint}/{bucket}/live/jobs/{job['id']}/outputs/"), out
        check_outputs(anon, outputs, HEADSQ.shape_zyx, HEADSQ.spacing_zyx_mm)

        s3 = seaweed_server.client()
        prefix = f"live/jobs/{job['id']}/"
        stored = [o["Key"] for o in s3.list_objects_v2(Bucket=bucket, Prefix=prefix).get("Contents", [])]
        assert f"{prefix}upload" in stored and len(stored) == 1 + len(outputs), stored  # one version only
        for name, out in outputs.items():  # the API's signed links stream the same objects
            with stack.client(base_url=api_links) as other:
                via_api = other.get(f"/v1/jobs/{job['id']}").json()
            link = next(o["url"] for o in via_api["outputs"] if o["name"] == name)
            assert link.startswith(f"{api_links}/v1/files/"), link
            direct = anon.get(out["url"]).content
            assert anon.get(link).content == direct and len(direct) == out["bytes"], name
            head = anon.head(link)
            assert head.status_code == 200 and head.headers["content-length"] == str(out["bytes"]), name
            assert head.headers["content-type"].startswith(out["media_type"]) and head.headers["etag"], name

        for data_dir in (stack.data_dir, worker_data):  # nothing of the job on a local disk
            assert not (data_dir / "jobs" / job["id"]).exists()
            scratch = data_dir / "scratch"
            assert not scratch.exists() or not any(scratch.iterdir()), list(scratch.iterdir())

        # re-orienting publishes a new version: the record moves to it, the old objects go
        before = {name: anon.get(out["url"]).content for name, out in outputs.items()}
        turn = {"first_slice": "inferior", "flip_lr": False, "flip_ap": True}
        assert client.post(f"/v1/jobs/{job['id']}/orient", json=turn).status_code == 202
        job = wait_for_job(client, job["id"], stack=stack, timeout=120, until=lambda j: j["stage"] == "done")
        assert job["state"] == "succeeded" and job["error"] is None, job
        after = {o["name"]: anon.get(o["url"]).content for o in job["outputs"]}
        assert after.keys() == before.keys() and all(after[n] != before[n] for n in after)
        stored = [o["Key"] for o in s3.list_objects_v2(Bucket=bucket, Prefix=prefix).get("Contents", [])]
        assert len(stored) == 1 + len(outputs), stored  # the upload and the new version only

        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert s3.list_objects_v2(Bucket=bucket, Prefix=prefix).get("KeyCount", 0) == 0
