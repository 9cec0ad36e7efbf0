"""Beyond one host, with every server real: an API, a redis-server, PostgreSQL (``postgres_server``), SeaweedFS
(``seaweed_server``) and two ``bonemesh worker`` processes, each with a data folder of its own (no disk shared
with the API or each other). Jobs spread over both workers (each job's ``runs`` names the worker and host of each
attempt); one worker is SIGKILLed in the middle of a job and the other finishes it; every output downloads from
the store's presigned links, and the store keeps one set of outputs per job."""

from __future__ import annotations

import socket
from typing import Any

import httpx

from tests.service.checks import check_outputs
from tests.service.conftest import HEADSQ, Scan, StackFactory
from tests.service.postgres import PostgresServer
from tests.service.procs import Proc, submit, wait_for_job, wait_until
from tests.service.seaweed import SeaweedServer

HEAVY_STAGES = ("gaussian", "isosurface", "islands", "decimate", "smooth", "normals")


def _node(proc: Proc) -> str:
    """The worker's Celery node name (``bonemesh worker``'s default: bonemesh@<host>-<pid>)."""
    return f"bonemesh@{socket.gethostname()}-{proc.pid}"


def _job_id(client: httpx.Client, scan: Scan) -> str:
    resp = submit(client, scan.path, scan.params)
    assert resp.status_code == 202, resp.text
    return str(resp.json()["id"])


def _check_from_store(anon: httpx.Client, job: dict[str, Any], s3: SeaweedServer, bucket: str, scan: Scan) -> None:
    outputs = {o["name"]: o for o in job["outputs"]}
    for out in outputs.values():
        assert out["url"].startswith(f"{s3.endpoint}/{bucket}/scale/jobs/{job['id']}/outputs/"), out
    check_outputs(anon, outputs, scan.shape_zyx, scan.spacing_zyx_mm)
    listed = s3.client().list_objects_v2(Bucket=bucket, Prefix=f"scale/jobs/{job['id']}/").get("Contents", [])
    assert len(listed) == 1 + len(outputs), [o["Key"] for o in listed]  # the upload and one set of outputs


def test_two_workers_on_postgres_and_s3_share_jobs_and_survive_a_kill(
    make_stack: StackFactory,
    postgres_server: PostgresServer,
    seaweed_server: SeaweedServer,
    long_scan: Scan,
) -> None:
    bucket = seaweed_server.make_bucket()
    env = {
        **seaweed_server.env(bucket, "scale"),
        "BONEMESH_DATABASE_URL": postgres_server.create_database(),
        "BONEMESH_DOWNLOAD_LINKS": "store",
    }
    _, stack = make_stack(server=False, workers=0, extra_env=env)
    stack.start_server()
    workers = [stack.start_worker({"BONEMESH_DATA_DIR": str(stack.root / f"host-{n}")}) for n in (1, 2)]
    for proc in workers:
        wait_until(lambda p=proc: " ready." in p.tail(20000), 120, f"{proc.name} to be ready", interval=0.2)

    with stack.client() as client, httpx.Client(timeout=60) as anon:
        short_ids = [_job_id(client, HEADSQ) for _ in range(2)]  # one each (one job at a time, no prefetch)...
        long_id = _job_id(client, long_scan)  # ...then the first free worker takes this one
        running = wait_for_job(
            client,
            long_id,
            stack=stack,
            timeout=180,
            interval=0.1,
            until=lambda j: j["state"] == "running" and j["stage"] in HEAVY_STAGES,
        )
        victim = next(p for p in workers if _node(p) == running["runs"][-1]["worker"])
        survivor = next(p for p in workers if p is not victim)
        victim.kill()  # SIGKILL to its whole process group, mid-pipeline

        long_job = wait_for_job(client, long_id, stack=stack, timeout=600)
        assert long_job["state"] == "succeeded" and long_job["attempts"] == 2, long_job
        lost, won = long_job["runs"]
        assert (lost["worker"], lost["outcome"]) == (_node(victim), "lost"), long_job["runs"]
        assert (won["worker"], won["outcome"]) == (_node(survivor), "succeeded"), long_job["runs"]
        assert lost["finished_at"] and won["host"] == lost["host"] == socket.gethostname()
        _check_from_store(anon, long_job, seaweed_server, bucket, long_scan)

        ran_by = set()
        for job_id in short_ids:
            job = wait_for_job(client, job_id, stack=stack, timeout=300)
            assert job["state"] == "succeeded" and [r["outcome"] for r in job["runs"]] == ["succeeded"], job
            ran_by.add(job["runs"][0]["worker"])
            _check_from_store(anon, job, seaweed_server, bucket, HEADSQ)
        assert ran_by == {_node(p) for p in workers}  # the jobs spread: each worker finished one

    for folder in (stack.data_dir, stack.root / "host-2" if survivor is workers[1] else stack.root / "host-1"):
        scratch = folder / "scratch"  # the survivor and the API left nothing behind
        assert not scratch.exists() or not any(scratch.iterdir()), list(scratch.iterdir())
        assert not (folder / "jobs").exists() or not any((folder / "jobs").iterdir())
