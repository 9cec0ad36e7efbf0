"""``python -m service.demo``: ``kill -TERM`` stops Redis, the API and the worker and removes the Redis folder;
the data folder is outside the repository by default."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.service.procs import free_port

REPO = Path(__file__).resolve().parents[1]


def _children(pid: int) -> set[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return set()
    return {int(p) for p in text.split()}


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="needs redis-server (scripts/_setup.sh installs it)")
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads child processes from /proc (Linux)")
def test_kill_term_stops_every_process_and_removes_the_redis_folder(tmp_path: Path) -> None:
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "BONEMESH_REDIS_URL"}
    env.update(TMPDIR=str(tmpdir), PYTHONPATH=str(REPO), BONEMESH_DEVICE="cpu")
    bin_dir = str(Path(sys.executable).parent)
    env["PATH"] = bin_dir + os.pathsep + env.get("PATH", "")
    demo = subprocess.Popen(
        [sys.executable, "-m", "service.demo", "--port", str(free_port()), "--data-dir", str(tmp_path / "data")],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        kids: set[int] = set()
        while time.monotonic() < deadline and demo.poll() is None:
            kids |= _children(demo.pid)
            if len(kids) >= 3 and any(tmpdir.glob("bonemesh-redis-*")):  # redis, API and worker started
                break
            time.sleep(0.1)
        assert demo.poll() is None, demo.stdout.read().decode() if demo.stdout else ""
        assert len(kids) >= 3 and any(tmpdir.glob("bonemesh-redis-*"))
        demo.send_signal(signal.SIGTERM)
        out, _ = demo.communicate(timeout=60)
    finally:
        if demo.poll() is None:
            demo.kill()
    text = out.decode()
    assert demo.returncode == 0, text
    assert "stopping (SIGTERM)" in text
    for _ in range(50):  # the demo waits for them; allow their reaping to show in /proc
        if not any(_alive(k) for k in kids):
            break
        time.sleep(0.1)
    assert not [k for k in kids if _alive(k)], f"still running: {kids}\n{text}"
    assert not list(tmpdir.glob("bonemesh-redis-*"))


def test_demo_data_folder_is_outside_the_repository(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from service.demo import default_data_dir

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert default_data_dir() == tmp_path / "cache" / "bonemesh-demo"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert REPO not in default_data_dir().resolve().parents
    ignored = subprocess.run(["git", "check-ignore", "-q", "bonemesh-data/x"], cwd=REPO, check=False)
    assert ignored.returncode == 0  # `bonemesh serve` run in the checkout writes there: git ignores it
