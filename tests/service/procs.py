"""Real processes for the service tests and ``benchmarks/service.py``: redis-server, ``bonemesh serve``, workers.

Nothing here imports pytest, the service or the worker: everything runs as a subprocess in its own process group
(``start_new_session``), with stdout and stderr in a log file, and is killed by group on close (and at interpreter
exit, so an interrupted run leaves no orphans).

    with RedisServer(tmp / "redis") as redis, ServiceStack(tmp / "stack", redis.url) as stack:
        stack.start_server()
        stack.start_worker()
        with stack.client("key-a") as client:
            job = submit(client, archive_path, {"iso": 1150, "spacing": [1.5, 3.2, 3.2]})
            job = wait_for_job(client, job["id"], stack=stack)
"""

from __future__ import annotations

import atexit
import contextlib
import importlib.metadata
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx

REPO = Path(__file__).resolve().parents[2]
TERMINAL_STATES = frozenset({"succeeded", "failed", "cancelled"})
API_KEYS = ("key-a", "key-b")
OUTPUT_NAMES = (
    "model.stl",
    "model.glb",
    "phone.glb",
    "ar.glb",
    "phone_meshopt.glb",
    "model.usdz",
    "preview.png",
    "report.json",
)

_LIVE: set[Proc] = set()  # every process group still running, killed at exit


class ProcessError(RuntimeError):
    """A helper process could not be started or died; the message carries its log tail."""


T = TypeVar("T")


_HANDED_OUT: set[int] = set()  # ports given to a caller in this process: never given twice


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range for outgoing connections' local ports (Linux), else IANA's."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 49152, 65535


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now (the caller binds it soon after).

    Drawn below the kernel's ephemeral range: a port the OS hands out for ``bind(0)`` is in that range, where any
    outgoing connection (a server's own clients, e.g. SeaweedFS's gRPC peers) may take it before the caller binds
    it. Below the range only another listener can, and a port is never handed out twice in one process.
    """
    low, _ = _ephemeral_range()
    top = max(low - 1, 11000)
    for _ in range(200):
        port = random.randint(10000, top)
        if port in _HANDED_OUT:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _HANDED_OUT.add(port)
        return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # a crowded machine: the OS's choice
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.1) -> Any:
    """Poll ``predicate`` until it returns a truthy value; TimeoutError naming ``what`` otherwise."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


class Proc:
    """One subprocess in its own process group, logging to ``log``.

    Args:
        name: a label for messages.
        argv: the command.
        log: file receiving stdout and stderr.
        env: the environment (default: inherited).
        cwd: working folder.
    """

    def __init__(
        self, name: str, argv: list[str], log: Path, env: dict[str, str] | None = None, cwd: Path | None = None
    ) -> None:
        self.name = name
        self.argv = argv
        self.log = log
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as fh:
            fh.write(f"$ {' '.join(argv)}\n".encode())
            fh.flush()
            self.popen = subprocess.Popen(
                argv,
                stdout=fh,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                cwd=cwd,
                start_new_session=True,
            )
        self.pid = self.popen.pid
        self.expected_exit = False
        _LIVE.add(self)

    def alive(self) -> bool:
        """Whether the leader is still running."""
        return self.popen.poll() is None

    def signal_group(self, sig: int) -> None:
        """Send ``sig`` to the whole process group (leader, prefork children, their helpers)."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.pid, sig)

    def kill(self) -> None:
        """SIGKILL the group and reap the leader (what a crash or the OOM killer does)."""
        self.expected_exit = True
        self.signal_group(signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.popen.wait(timeout=10)
        self._wait_group_gone(5.0)
        _LIVE.discard(self)

    def stop(self, grace: float = 5.0) -> None:
        """SIGTERM the group, then SIGKILL it after ``grace`` seconds; always leaves no member behind."""
        self.expected_exit = True
        if self.alive():
            self.signal_group(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.popen.wait(timeout=grace)
        self.signal_group(signal.SIGKILL)  # stragglers of the group even when the leader exited
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.popen.wait(timeout=10)
        self._wait_group_gone(5.0)
        _LIVE.discard(self)

    def _wait_group_gone(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                os.killpg(self.pid, 0)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.05)

    def tail(self, chars: int = 6000) -> str:
        """The end of the log."""
        try:
            text = self.log.read_text(errors="replace")
        except FileNotFoundError:
            return "(no log)"
        return text if len(text) <= chars else "..." + text[-chars:]

    def describe(self) -> str:
        """State and exit code, for messages."""
        rc = self.popen.poll()
        return f"{self.name} (pid {self.pid}): " + ("running" if rc is None else f"exited with {rc}")


@atexit.register
def _kill_leftovers() -> None:
    for proc in list(_LIVE):
        proc.signal_group(signal.SIGKILL)


def apt_install(packages: list[str], found: Callable[[], T | None]) -> T | None:
    """``found()``, after installing ``packages`` with apt-get (as root, where apt-get exists) when it gives None:
    first without, then after ``apt-get update``. None when still not found."""
    hit = found()
    if hit is not None or not shutil.which("apt-get") or os.geteuid() != 0:
        return hit
    install = ["apt-get", "install", "-y", "-qq", *packages]
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmds in ([install], [["apt-get", "update", "-qq"], install]):
        for cmd in cmds:
            subprocess.run(cmd, capture_output=True, timeout=900, check=False, env=env)
        hit = found()
        if hit is not None:
            return hit
    return None


def find_redis_server(path: str | os.PathLike[str] | None = None, *, install: bool = True) -> str:
    """The redis-server executable: ``path``, on PATH, or installed with apt-get (as root) when missing.

    Raises:
        ProcessError: not found and not installable here.
    """
    if path:
        if not Path(path).is_file():
            raise ProcessError(f"redis-server not found at {path}")
        return str(Path(path).absolute())  # the server starts in its own working folder

    def where() -> str | None:
        return shutil.which("redis-server") or next(
            (p for p in ("/usr/bin/redis-server", "/usr/local/bin/redis-server") if Path(p).is_file()), None
        )

    found = apt_install(["redis-server"], where) if install else where()
    if found:
        return found
    raise ProcessError(
        "redis-server is not installed and could not be installed with apt-get "
        "(install it: `apt-get install -y redis-server`, or pass its path)"
    )


def redis_ping(port: int, timeout: float = 0.5) -> bool:
    """Whether a Redis server answers PING on 127.0.0.1:port."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            s.sendall(b"PING\r\n")
            return s.recv(16).startswith(b"+PONG")
    except OSError:
        return False


class RedisServer:
    """A throwaway redis-server on a free loopback port, without persistence (a restart loses every message).

    Args:
        workdir: its folder (log, working directory).
        executable: redis-server path (default: found or installed by :func:`find_redis_server`).
    """

    def __init__(self, workdir: Path, executable: str | None = None) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.executable = find_redis_server(executable)
        self.port = free_port()
        self.proc: Proc | None = None
        self.starts = 0
        self.start()

    @property
    def url(self) -> str:
        """Broker URL of database 0."""
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        """Start it on ``self.port`` and wait until it answers PING."""
        self.starts += 1
        argv = [self.executable, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
        argv += ["--dir", str(self.workdir), "--protected-mode", "no"]
        self.proc = Proc(f"redis-server:{self.port}", argv, self.workdir / "redis.log", cwd=self.workdir)
        try:
            wait_until(lambda: redis_ping(self.port) or not self.proc.alive(), 20, "redis-server to answer PING")
        except TimeoutError as exc:
            raise ProcessError(f"{exc}\n{self.proc.tail()}") from None
        if not self.proc.alive():
            raise ProcessError(f"redis-server exited at start:\n{self.proc.tail()}")

    def stop(self) -> None:
        """Kill it (SIGKILL: no shutdown save either way)."""
        if self.proc is not None:
            self.proc.kill()
            wait_until(lambda: not redis_ping(self.port), 10, "redis-server to go away")

    def restart(self) -> None:
        """Kill and start again on the same port: queued messages are gone."""
        self.stop()
        self.start()

    def close(self) -> None:
        """Stop it."""
        if self.proc is not None:
            self.proc.stop(grace=2)

    def __enter__(self) -> RedisServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def bonemesh_argv() -> list[str]:
    """The ``bonemesh`` command: the console script beside this interpreter, else its entry point run here."""
    script = Path(sys.executable).parent / "bonemesh"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    target = None
    with contextlib.suppress(Exception):
        (ep,) = importlib.metadata.entry_points(group="console_scripts", name="bonemesh")
        target = ep.value
    if target is None:  # not installed: the entry point declared in the checkout's pyproject
        target = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]["bonemesh"]
    module, _, func = target.partition(":")
    return [sys.executable, "-c", f"import sys, {module} as m; sys.exit(m.{func}())"]


class ServiceStack:
    """An API server and workers sharing one data folder, database, secret and queue.

    Args:
        root: folder for the data, the database and the logs.
        redis_url: the broker.
        device: BONEMESH_DEVICE for workers.
        stale_seconds, reconcile_seconds: how fast lost jobs are noticed (short for tests).
        extra_env: more (or overriding) variables, e.g. ``{"BONEMESH_URL_TTL_SECONDS": "2"}``.
    """

    def __init__(
        self,
        root: Path,
        redis_url: str,
        *,
        device: str = "cpu",
        stale_seconds: float = 6,
        reconcile_seconds: float = 1,
        max_upload_bytes: int = 64 << 20,
        extra_env: dict[str, str] | None = None,
    ) -> None:
        self.root = Path(root)
        self.data_dir = self.root / "data"
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.log_dir = self.root / "logs"
        self.redis_url = redis_url
        env = {k: v for k, v in os.environ.items() if not k.startswith("BONEMESH_")}
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
        env["PYTHONUNBUFFERED"] = "1"
        env.update(
            {
                "BONEMESH_REDIS_URL": redis_url,
                "BONEMESH_DATA_DIR": str(self.data_dir),
                "BONEMESH_DATABASE_URL": f"sqlite:///{self.data_dir / 'bonemesh.db'}",
                "BONEMESH_API_KEYS": ",".join(API_KEYS),
                "BONEMESH_SECRET_KEY": "test-secret-" + os.urandom(8).hex(),
                "BONEMESH_DEVICE": device,
                "BONEMESH_MAX_UPLOAD_BYTES": str(max_upload_bytes),
                "BONEMESH_STALE_SECONDS": str(stale_seconds),
                "BONEMESH_RECONCILE_SECONDS": str(reconcile_seconds),
                "BONEMESH_QUEUE": f"bonemesh-test-{os.getpid()}-{os.urandom(3).hex()}",
                "BONEMESH_JOB_SOFT_TIME_LIMIT": "900",
                "BONEMESH_JOB_TIME_LIMIT": "960",
            }
        )
        env.update(extra_env or {})
        self.env = env
        self.servers: list[Proc] = []
        self.workers: list[Proc] = []
        self.base_url = ""

    # -- processes --------------------------------------------------------------------------------------------
    def _count(self) -> int:
        return len(self.servers) + len(self.workers) + 1

    def start_server(self, port: int | None = None, extra_env: dict[str, str] | None = None, workers: int = 1) -> str:
        """Start ``bonemesh serve`` (with ``workers`` API processes) and wait for /healthz; returns its base URL (the
        first becomes ``base_url``)."""
        port = port or free_port()
        argv = [*bonemesh_argv(), "serve", "--host", "127.0.0.1", "--port", str(port), "--workers", str(workers)]
        proc = Proc(
            f"server:{port}",
            argv,
            self.log_dir / f"server-{self._count()}.log",
            {**self.env, **(extra_env or {})},
            cwd=self.root,
        )
        self.servers.append(proc)
        url = f"http://127.0.0.1:{port}"

        def healthy() -> bool:
            if not proc.alive():
                raise ProcessError(f"{proc.describe()} at start:\n{proc.tail()}")
            try:
                return httpx.get(f"{url}/healthz", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        try:
            wait_until(healthy, 60, f"{url}/healthz", interval=0.2)
        except TimeoutError as exc:
            raise ProcessError(f"{exc}\n{proc.tail()}") from None
        if not self.base_url:
            self.base_url = url
        return url

    def start_worker(self, extra_env: dict[str, str] | None = None) -> Proc:
        """Start ``bonemesh worker`` (not waited for: jobs queue until it consumes them)."""
        argv = [*bonemesh_argv(), "worker"]
        proc = Proc(
            f"worker-{len(self.workers) + 1}",
            argv,
            self.log_dir / f"worker-{self._count()}.log",
            {**self.env, **(extra_env or {})},
            cwd=self.root,
        )
        self.workers.append(proc)
        return proc

    def check_alive(self) -> None:
        """ProcessError when a process died that nobody meant to stop."""
        for proc in [*self.servers, *self.workers]:
            if not proc.expected_exit and not proc.alive():
                raise ProcessError(f"{proc.describe()} unexpectedly:\n{proc.tail()}")

    def logs(self, chars: int = 5000) -> str:
        """The tails of every process log, for failure messages."""
        parts = []
        for proc in [*self.servers, *self.workers]:
            parts.append(f"----- {proc.describe()} log {proc.log} -----\n{proc.tail(chars)}")
        return "\n".join(parts)

    def close(self) -> None:
        """Stop every process (workers first)."""
        for proc in [*self.workers, *self.servers]:
            proc.stop(grace=3)

    def __enter__(self) -> ServiceStack:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- HTTP -------------------------------------------------------------------------------------------------
    def client(self, key: str | None = API_KEYS[0], base_url: str | None = None, timeout: float = 60) -> httpx.Client:
        """An HTTP client for the API, sending ``X-API-Key: key`` (None: no key)."""
        headers = {"X-API-Key": key} if key is not None else {}
        return httpx.Client(base_url=base_url or self.base_url, headers=headers, timeout=timeout)


def submit(
    client: httpx.Client,
    archive: Path | bytes,
    params: dict[str, Any] | None = None,
    filename: str | None = None,
    extra: dict[str, str] | None = None,
) -> httpx.Response:
    """POST /v1/jobs with the archive (a path, or bytes), optional params and other form fields (``extra``, e.g.
    ``callback_url``); returns the raw response."""
    if isinstance(archive, Path):
        name = filename or archive.name
        with open(archive, "rb") as fh:
            return _post(client, (name, fh, "application/octet-stream"), params, extra)
    return _post(client, (filename or "upload.zip", archive, "application/octet-stream"), params, extra)


def _post(
    client: httpx.Client, file: tuple[str, Any, str], params: dict[str, Any] | None, extra: dict[str, str] | None
) -> httpx.Response:
    data = {"params": json.dumps(params)} if params is not None else {}
    data.update(extra or {})
    return client.post("/v1/jobs", files={"file": file}, data=data or None)


def wait_for_job(
    client: httpx.Client,
    job_id: str,
    *,
    stack: ServiceStack | None = None,
    timeout: float = 300,
    until: Callable[[dict[str, Any]], bool] = lambda job: job["state"] in TERMINAL_STATES,
    interval: float = 0.25,
    on_poll: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Poll GET /v1/jobs/{id} until ``until(job)``; TimeoutError with the last state and the process logs otherwise.

    Raises ProcessError as soon as a process of ``stack`` died unexpectedly.
    """
    deadline = time.monotonic() + timeout
    job: dict[str, Any] = {}
    while True:
        if stack is not None:
            stack.check_alive()
        resp = client.get(f"/v1/jobs/{job_id}")
        if resp.status_code != 200:
            raise AssertionError(f"GET /v1/jobs/{job_id} -> {resp.status_code}: {resp.text}")
        job = resp.json()
        if on_poll is not None:
            on_poll(job)
        if until(job):
            return job
        if time.monotonic() > deadline:
            logs = f"\n{stack.logs()}" if stack is not None else ""
            raise TimeoutError(f"job {job_id} not done after {timeout:.0f} s; last seen: {json.dumps(job)}{logs}")
        time.sleep(interval)


@contextlib.contextmanager
def running_stack(
    root: Path, *, redis_executable: str | None = None, workers: int = 1, **kwargs: Any
) -> Iterator[tuple[RedisServer, ServiceStack]]:
    """Redis, one API server and ``workers`` workers, all stopped on exit."""
    with RedisServer(root / "redis", redis_executable) as redis, ServiceStack(root, redis.url, **kwargs) as stack:
        stack.start_server()
        for _ in range(workers):
            stack.start_worker()
        yield redis, stack
