"""docker-compose.yml and the worker's container entry: one worker per GPU, each with a health check."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
ENTRY = REPO / "docker" / "worker-entry.sh"


def _compose() -> dict:
    return yaml.safe_load((REPO / "docker-compose.yml").read_text())  # resolves the anchors and << merges


def test_compose_gpu_workers_claim_their_own_gpu_and_are_health_checked() -> None:
    services = _compose()["services"]
    gpu, cpu = services["worker"], services["worker-cpu"]
    assert gpu["command"] == cpu["command"] == ["bonemesh-worker-entry"]
    reservation = gpu["deploy"]["resources"]["reservations"]["devices"][0]
    assert reservation["count"] == "all" and "device_ids" not in reservation  # the entry script picks one
    assert str(gpu["deploy"]["replicas"]) == "${BONEMESH_GPUS:-1}"
    assert gpu["environment"]["BONEMESH_GPU_LOCKS"] == "/run/bonemesh-gpus"
    assert "gpu-locks:/run/bonemesh-gpus" in gpu["volumes"]
    assert cpu["environment"]["BONEMESH_DEVICE"] == "cpu" and "deploy" not in cpu
    for worker in (gpu, cpu):
        check = worker["healthcheck"]
        assert check["test"][0] == "CMD-SHELL"
        assert "celery -A worker.app inspect ping" in check["test"][1] and "bonemesh@$$(hostname)" in check["test"][1]
        assert worker["environment"]["BONEMESH_REDIS_URL"] == "redis://redis:6379/0"  # the shared env anchor
    assert "gpu-locks" in _compose()["volumes"]
    dockerfile = (REPO / "Dockerfile").read_text()
    assert "COPY docker/worker-entry.sh /usr/local/bin/bonemesh-worker-entry" in dockerfile


def test_compose_scale_profile_runs_postgresql_and_an_s3_store_that_every_process_is_pointed_at() -> None:
    compose = _compose()
    services = compose["services"]
    for name in ("db", "s3", "s3-init"):
        assert services[name]["profiles"] == ["scale"], name
    assert services["db"]["image"].startswith("postgres:") and "healthcheck" in services["db"]
    assert services["s3"]["command"][:2] == ["server", "-dir=/data"] and "-s3" in services["s3"]["command"]
    assert services["s3-init"]["depends_on"]["s3"]["condition"] == "service_healthy"
    identities = compose["configs"]["s3-identities"]["content"]
    assert "${AWS_ACCESS_KEY_ID" in identities and "${AWS_SECRET_ACCESS_KEY" in identities
    # the API and every worker read the database and the store from the same variables (embedded defaults kept)
    for name in ("api", "worker", "worker-cpu", "worker-opencl"):
        env = services[name]["environment"]
        assert env["BONEMESH_DATABASE_URL"] == "${BONEMESH_DATABASE_URL:-sqlite:////data/bonemesh.db}", name
        assert env["BONEMESH_STORAGE_URL"] == "${BONEMESH_STORAGE_URL:-}", name
        assert {"BONEMESH_S3_ENDPOINT_URL", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"} <= set(env), name
    assert services["worker-opencl"]["environment"]["BONEMESH_DEVICE"] == "opencl"
    dockerfile = (REPO / "Dockerfile").read_text()
    assert "ARG BONEMESH_OPENCL=0" in dockerfile and "pocl-opencl-icd" in dockerfile and "s3" in dockerfile


def test_compose_config_validates_when_docker_compose_is_present(tmp_path: Path) -> None:
    docker = shutil.which("docker")
    if docker is None or subprocess.run([docker, "compose", "version"], capture_output=True).returncode != 0:
        pytest.skip("docker compose is not installed here (the YAML is checked by the test above)")
    env = {**os.environ, "BONEMESH_API_KEYS": "k", "BONEMESH_SECRET_KEY": "s", "BONEMESH_GPUS": "2"}
    out = subprocess.run(
        [docker, "compose", "-f", str(REPO / "docker-compose.yml"), "config", "--format", "json"],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    assert '"replicas": 2' in out.stdout


def _fake_bonemesh(tmp_path: Path) -> None:
    """A `bonemesh` in tmp_path/bin that records what the entry script handed it, then lives until killed."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    fake = bindir / "bonemesh"
    fake.write_text(
        '#!/bin/sh\necho "argv=$*" > "$REPORT"\n'
        'echo "device=$BONEMESH_DEVICE visible=${CUDA_VISIBLE_DEVICES:-} cache=${WARP_CACHE_PATH:-}" >> "$REPORT"\n'
        "exec sleep 60\n"
    )
    fake.chmod(0o755)


def _start(tmp_path: Path, name: str, **env: str) -> tuple[subprocess.Popen[bytes], Path]:
    report = tmp_path / f"{name}.txt"
    bindir = tmp_path / "bin"
    if not bindir.exists():
        _fake_bonemesh(tmp_path)
    proc = subprocess.Popen(["sh", str(ENTRY)], env=_env(tmp_path, report, env), stderr=subprocess.DEVNULL)
    return proc, report


def _env(tmp_path: Path, report: Path, env: dict[str, str]) -> dict[str, str]:
    return {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}", "REPORT": str(report), **env}


def _wait_report(report: Path) -> str:
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if report.exists() and report.read_text().count("\n") >= 2:
            return report.read_text()
        time.sleep(0.05)
    raise AssertionError(f"{report.name}: the entry script never started the worker")


@pytest.mark.skipif(shutil.which("flock") is None, reason="flock (util-linux) is not installed")
def test_entry_script_gives_each_worker_its_own_gpu(tmp_path: Path) -> None:
    locks = tmp_path / "locks"
    common = {"BONEMESH_GPUS": "2", "BONEMESH_GPU_LOCKS": str(locks), "WARP_CACHE_PATH": "/cache"}
    procs = []
    try:
        a, ra = _start(tmp_path, "a", **common)
        procs.append(a)
        got_a = _wait_report(ra)
        b, rb = _start(tmp_path, "b", **common)
        procs.append(b)
        got_b = _wait_report(rb)
        gpus = {line.split("visible=")[1].split()[0] for line in (got_a, got_b)}
        assert gpus == {"0", "1"}, (got_a, got_b)  # two workers, two different GPUs
        for got in (got_a, got_b):
            assert "device=cuda:0" in got and f"argv=worker --hostname bonemesh@{os.uname().nodename}" in got
            assert "cache=/cache/gpu" in got  # a Warp kernel cache per GPU
        env_c = _env(tmp_path, tmp_path / "c.txt", common)  # a third replica on a 2-GPU host
        c = subprocess.run(["sh", str(ENTRY)], env=env_c, capture_output=True, text=True, timeout=20, check=False)
        assert c.returncode == 1 and "all 2 GPU(s) are taken" in c.stderr
        a.kill()  # a worker dies: its GPU is free again
        a.wait(timeout=10)
        d, rd = _start(tmp_path, "d", **common)
        procs.append(d)
        freed = got_a.split("visible=")[1].split()[0]
        assert f"visible={freed}" in _wait_report(rd)
    finally:
        for p in procs:
            p.kill()
            p.wait(timeout=10)


def test_entry_script_cpu_worker_claims_nothing(tmp_path: Path) -> None:
    proc, report = _start(tmp_path, "cpu", BONEMESH_DEVICE="cpu", BONEMESH_GPU_LOCKS=str(tmp_path / "locks"))
    try:
        got = _wait_report(report)
        assert "device=cpu visible= " in got and f"argv=worker --hostname bonemesh@{os.uname().nodename}" in got
        assert not (tmp_path / "locks").exists()
    finally:
        proc.kill()
        proc.wait(timeout=10)
