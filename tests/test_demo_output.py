"""``python -m service.demo --exit``: the terminal shows the demo's own lines only, never Celery's start-up banner
nor its warning about a worker with superuser privileges (issue 45); the worker's output is in ``worker.log``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.service.procs import free_port

REPO = Path(__file__).resolve().parents[1]
CELERY_LINES = ("-------------- ", "[queues]", "[tasks]", "superuser privileges", "celery@", "transport:")


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="needs redis-server (scripts/_setup.sh installs it)")
def test_demo_prints_its_own_lines_only(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "BONEMESH_REDIS_URL"}
    env.update(PYTHONPATH=str(REPO), BONEMESH_DEVICE="cpu", TMPDIR=str(tmp_path))
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    data = tmp_path / "data"
    run = subprocess.run(
        [sys.executable, "-m", "service.demo", "--exit", "--port", str(free_port()), "--data-dir", str(data)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    text = run.stdout + run.stderr
    assert run.returncode == 0, text
    assert "done in" in run.stdout and "phone.glb" in run.stdout, text
    assert not [line for line in CELERY_LINES if line in text], text
    assert f"the worker's log: {data.resolve() / 'worker.log'}" in run.stdout, text
    log = (data / "worker.log").read_text()
    assert "[queues]" in log  # the banner is kept, in the log
    if os.geteuid() == 0:
        assert "superuser privileges" in log  # true, and kept where an operator looks
