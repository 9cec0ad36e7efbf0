"""Scaling parts, with real processes: several API processes on one port, and a worker that warms its device up
before its first job (``BONEMESH_WARMUP``)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.service.checks import assert_succeeded
from tests.service.conftest import HEADSQ, StackFactory
from tests.service.procs import submit, wait_for_job, wait_until


def test_two_api_processes_and_a_warm_worker(make_stack: StackFactory) -> None:
    _, stack = make_stack(server=False, workers=0)
    url = stack.start_server(workers=2)
    worker = stack.start_worker({"BONEMESH_WARMUP": "true", "BONEMESH_DEVICE": "cpu"})
    wait_until(lambda: "device cpu warm in" in worker.tail(20000), 240, "the worker's warm-up", interval=0.2)

    def post(_: int) -> str:
        with stack.client() as client:  # one connection each: the uploads arrive together
            resp = submit(client, HEADSQ.path, HEADSQ.params)
            assert resp.status_code == 202, resp.text
            return resp.json()["id"]

    with ThreadPoolExecutor(4) as pool:
        ids = list(pool.map(post, range(4)))
    with stack.client() as client:
        for job_id in ids:
            outputs = assert_succeeded(wait_for_job(client, job_id, stack=stack, timeout=600), url)
            link = httpx.get(outputs["phone.glb"]["url"], timeout=30)  # signed by either process, served by either
            assert link.status_code == 200 and link.content[:4] == b"glTF"
    assert "already taken" not in worker.tail(50000)  # each job ran once


def test_warm_up_is_on_for_every_device_unless_set() -> None:
    from core.settings import Settings
    from worker.app import warms_up

    assert warms_up(Settings(device="cuda:1"))
    assert warms_up(Settings(device="cpu"))  # Warp's CPU modules: the first job would load them
    assert warms_up(Settings(device="cpu", warmup="true"))
    assert not warms_up(Settings(device="cuda:0", warmup="false"))
    assert Settings().warmup_volume_bytes == 512 << 20
    assert Settings(warmup_volume_bytes="1GiB").warmup_volume_bytes == 1 << 30  # read once, as a byte count
    assert Settings(warmup_volume_bytes="0").warmup_volume_bytes == 0
    with pytest.raises(ValueError, match="byte count"):
        Settings(warmup_volume_bytes="lots")
