"""A zip of PNG slices decoded while it is uploaded (``BONEMESH_DECODE_DURING_UPLOAD``, ``engine.io.predecode``): the
API leaves the decoded slices beside the upload, the worker loads them instead of the zip (and removes them), and
the model is the same; a refused upload keeps nothing of them, and the setting switches them off. The bundled CT head
is smaller than ``BONEMESH_PREDECODE_MIN_BYTES``, so these tests set it to 0 (every upload), but the one that checks
the default leaves small scans to the worker."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
from fastapi.testclient import TestClient

from core.settings import Settings
from engine.data import HEADSQ_ZIP
from tests.service.checks import assert_succeeded
from tests.service.conftest import HEADSQ, app_client, zip_to_tar_gz
from tests.service.procs import ServiceStack, submit, wait_for_job

KEY = {"X-API-Key": "key-a"}
EVERY = {"predecode_min_bytes": 0}  # the bundled head's 0.3 MB zip decoded during its upload too
PARAMS = {"iso": 1150, "spacing": list(HEADSQ.spacing_zyx_mm)}


def _post(client: TestClient, params: Any = PARAMS, data: bytes | None = None) -> Any:
    body = HEADSQ_ZIP.read_bytes() if data is None else data
    return client.post(
        "/v1/jobs",
        files={"file": ("headsq.zip", body, "application/zip")},
        data={"params": params if isinstance(params, str) else json.dumps(params)},
        headers=KEY,
    )


def _job_files(data_dir: Path) -> list[str]:
    return sorted(p.relative_to(data_dir / "jobs").as_posix() for p in (data_dir / "jobs").rglob("*") if p.is_file())


def test_the_api_leaves_the_decoded_slices_beside_the_upload(tmp_path: Path) -> None:
    with app_client(tmp_path, **EVERY) as client:
        resp = _post(client)
        assert resp.status_code == 202, resp.text
        job = resp.json()["id"]
        assert _job_files(tmp_path) == [f"{job}/upload", f"{job}/upload.slices", f"{job}/upload.slices.json"]
        manifest = json.loads((tmp_path / "jobs" / job / "upload.slices.json").read_text())
        assert manifest["shape"] == [93, 64, 64] and manifest["order"] == list(range(93))
        assert manifest["layout"] == "rows"  # the default device (auto): the worker's GPU, if any, unfilters them


def test_the_layout_follows_the_workers_device() -> None:
    """Rows (only inflated) where the workers may have a GPU to unfilter them; samples for CPU workers, and where
    PNG slices are not to be unfiltered on a GPU (``png_decoder``)."""
    from service.intake import predecode_layout

    def layout(**kw: Any) -> str:
        return predecode_layout(_settings(Path("/tmp"), **kw))

    assert layout() == layout(device="cuda:0") == layout(device="opencl:0") == "rows"
    assert layout(device="cpu") == layout(png_decoder="libpng") == layout(png_decoder="pillow") == "planes"


def test_a_refused_upload_keeps_none_of_them(tmp_path: Path) -> None:
    with app_client(tmp_path / "a", **EVERY) as client:  # refused after the whole body was read and decoded
        resp = _post(client, params='{"iso": "bone"}')
        assert resp.status_code == 422, resp.text
        assert _job_files(tmp_path / "a") == []
    with app_client(tmp_path / "b", max_upload_bytes=200_000, **EVERY) as client:  # refused half way
        resp = _post(client)
        assert resp.status_code == 413, resp.text
        assert _job_files(tmp_path / "b") == []


def _settings(data_dir: Path, **kw: Any) -> Settings:
    return Settings(
        data_dir=data_dir, api_keys=["key-a"], secret_key="s" * 32, redis_url="redis://127.0.0.1:1/0",
        reconcile_seconds=3600, **{**EVERY, **kw},
    )  # fmt: skip


def test_a_small_upload_is_left_to_the_worker(tmp_path: Path) -> None:
    """By default (``BONEMESH_PREDECODE_MIN_BYTES``, 64 MiB) the bundled head's 0.3 MB zip is not decoded during its
    upload, a request of unknown length or of the bound's size is, and the worker's model is the same either way
    (``test_the_worker_loads_them_and_the_model_is_the_same``)."""
    from service.intake import start_decoder
    from service.services import Services

    with app_client(tmp_path) as client:
        resp = _post(client)
        assert resp.status_code == 202, resp.text
        assert _job_files(tmp_path) == [f"{resp.json()['id']}/upload"]
    settings = _settings(tmp_path / "s", predecode_min_bytes=1 << 20)
    svc = Services(settings)
    try:
        for job, (length, decoded) in enumerate((("1048575", False), ("1048576", True), (None, True))):
            decoder = start_decoder(svc, f"{job:032x}", length)
            assert (decoder is not None) is decoded, length
            if decoder is not None:
                decoder.abort()
    finally:
        svc.close()


def test_the_setting_switches_it_off(tmp_path: Path) -> None:
    from service.app import create_app

    with TestClient(create_app(_settings(tmp_path, decode_during_upload=False))) as client:
        resp = _post(client)
        assert resp.status_code == 202, resp.text
        assert _job_files(tmp_path) == [f"{resp.json()['id']}/upload"]


def test_a_child_process_decodes_them_or_the_apis_threads(tmp_path: Path, monkeypatch: Any) -> None:
    """``BONEMESH_PREDECODE_PROCESS`` (default on): a child process decodes the slices; off: threads of the API;
    the same sidecar either way."""
    from engine.io.predecode_proc import DecoderProcess
    from service.app import create_app

    verdicts: list[bool] = []
    finish = DecoderProcess.finish

    def spy(self: DecoderProcess, length: int) -> bool:
        verdicts.append(finish(self, length))
        return verdicts[-1]

    monkeypatch.setattr(DecoderProcess, "finish", spy)
    sidecars = []
    for process in (True, False):
        data_dir = tmp_path / str(process)
        with TestClient(create_app(_settings(data_dir, predecode_process=process))) as client:
            resp = _post(client)
            assert resp.status_code == 202, resp.text
            job = data_dir / "jobs" / resp.json()["id"]
            assert verdicts == [True]  # the child's, the first time only
            sidecars.append([(job / name).read_bytes() for name in ("upload.slices", "upload.slices.json")])
    assert sidecars[0] == sidecars[1]


def test_a_child_that_dies_never_costs_the_upload(tmp_path: Path, monkeypatch: Any) -> None:
    """The child killed as the upload begins: the job is accepted all the same, without the decoded slices (the
    worker decodes the zip)."""
    import os
    import signal

    from engine.io.predecode_proc import DecoderChildren, DecoderProcess

    start = DecoderChildren.start
    pids = []

    def killed(self: DecoderChildren, *args: Any) -> DecoderProcess | None:
        child = start(self, *args)
        assert child is not None
        os.kill(child.pid, signal.SIGKILL)
        pids.append(child.pid)
        return child

    monkeypatch.setattr(DecoderChildren, "start", killed)
    with app_client(tmp_path, **EVERY) as client:
        resp = _post(client)
        assert resp.status_code == 202, resp.text
        assert pids and _job_files(tmp_path) == [f"{resp.json()['id']}/upload"]


def test_the_worker_loads_them_and_the_model_is_the_same(stack: ServiceStack, anon: httpx.Client) -> None:
    """The same slices as a zip (decoded during the upload: samples from this stack's API, whose workers are CPU
    ones; rows from a second API that expects GPU workers, unfiltered by the CPU worker's libpng) and as a tar.gz
    (decoded by the worker): the same files, byte for byte, but for the report, which says where the slices came
    from."""
    every = {"BONEMESH_PREDECODE_MIN_BYTES": "0"}
    planes_api = stack.start_server(extra_env=every)
    rows_api = stack.start_server(extra_env={**every, "BONEMESH_DEVICE": "auto"})
    jobs = {}
    with httpx.Client(base_url=planes_api, headers=KEY, timeout=60) as client_planes:
        for name, body in (("headsq.zip", HEADSQ_ZIP.read_bytes()), ("headsq.tar.gz", zip_to_tar_gz(HEADSQ_ZIP))):
            jobs[name] = _through_worker(stack, client_planes, name, body)
    with httpx.Client(base_url=rows_api, headers=KEY, timeout=60) as client_rows:
        jobs["rows.zip"] = _through_worker(stack, client_rows, "rows.zip", HEADSQ_ZIP.read_bytes())
    plain = jobs["headsq.tar.gz"]
    reports = {k: anon.get(v["report.json"]["url"]).json() for k, v in jobs.items()}
    assert reports["headsq.zip"]["input"]["source"]["decoded_during_upload"] is True
    assert reports["rows.zip"]["input"]["source"]["decoded_during_upload"] is True
    assert "decoded_during_upload" not in reports["headsq.tar.gz"]["input"]["source"]
    for fast in (jobs["headsq.zip"], jobs["rows.zip"]):
        assert sorted(fast) == sorted(plain)
        for name in fast:
            if name != "report.json":
                assert anon.get(fast[name]["url"]).content == anon.get(plain[name]["url"]).content, name


def _through_worker(stack: ServiceStack, client: httpx.Client, name: str, body: bytes) -> dict[str, Any]:
    """Upload, wait for the worker, and check the sidecar was read once and removed; the job's outputs."""
    resp = submit(client, body, PARAMS, filename=name)
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client, resp.json()["id"], stack=stack, timeout=300)
    folder = stack.data_dir / "jobs" / job["id"]
    assert (folder / "upload").is_file() and not list(folder.glob("upload.slices*"))  # read once, then removed
    return assert_succeeded(job, str(client.base_url).rstrip("/"))
