"""The one-machine demo: start Redis, the API and a worker, upload the bundled CT scan over HTTP, wait for the
job, and print the download links (``bash scripts/demo.sh`` runs this).

    python -m service.demo [--port 8000] [--data-dir DIR] [--exit]

Redis: ``BONEMESH_REDIS_URL`` when set (an existing server), else a private ``redis-server`` on a free port
(installed with apt-get when missing). The API and the worker are the real ``bonemesh serve`` and
``bonemesh worker`` processes. Without ``--exit`` everything keeps running (so the links work) until Ctrl-C or
``kill -TERM`` (or SIGHUP): either stops Redis, the API and the worker and removes the private Redis folder.
The data (uploads, outputs, database) go to ``--data-dir``, by default ``$XDG_CACHE_HOME/bonemesh-demo``
(``~/.cache/bonemesh-demo``), outside the repository.

The terminal shows the demo's own lines only: the worker's output (Celery's start-up banner, its log, and, when the
demo runs as root, as in a container, Celery's warning about a worker with superuser privileges) goes to
``worker.log`` in the data folder, whose path is printed, and whose last lines are printed when the worker stops or
the job fails. The warning stays in the log on purpose: it is true (a worker should not run as root in production),
but a demo run as root is expected, and the worker accepts JSON messages only (no pickle), so Celery only warns.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any

from core.settings import DEV_API_KEY


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _redis_server() -> str:
    found = shutil.which("redis-server")
    if found:
        return found
    print("redis-server is missing: installing it with apt-get ...", flush=True)  # noqa: T201
    sudo = [] if os.geteuid() == 0 else ["sudo"]
    subprocess.run([*sudo, "apt-get", "install", "-y", "-q", "redis-server"], check=False)
    if not shutil.which("redis-server"):
        subprocess.run([*sudo, "apt-get", "update", "-q"], check=False)
        subprocess.run([*sudo, "apt-get", "install", "-y", "-q", "redis-server"], check=False)
    found = shutil.which("redis-server")
    if not found:
        raise SystemExit("could not install redis-server; install it, or set BONEMESH_REDIS_URL to a running Redis")
    return found


def _request(method: str, url: str, key: str, body: bytes | None = None, ctype: str | None = None) -> Any:
    req = urllib.request.Request(url, data=body, method=method, headers={"X-API-Key": key})
    if ctype:
        req.add_header("Content-Type", ctype)
    with urllib.request.urlopen(req, timeout=60) as resp:
        return json.loads(resp.read())


def _multipart(path: Path, params: dict[str, Any]) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = [
        f'--{boundary}\r\nContent-Disposition: form-data; name="params"\r\n\r\n{json.dumps(params)}\r\n'.encode(),
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{path.name}"\r\n'
        "Content-Type: application/zip\r\n\r\n".encode(),
        path.read_bytes(),
        f"\r\n--{boundary}--\r\n".encode(),
    ]
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def _tail(path: Path, lines: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def _wait_http(url: str, procs: list[subprocess.Popen[bytes]], timeout: float, worker_log: Path) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if any(p.poll() is not None for p in procs):
            raise SystemExit(
                f"a service process stopped while starting; the worker's log ({worker_log}):\n{_tail(worker_log)}"
            )
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except (urllib.error.URLError, OSError):
            time.sleep(0.2)
    raise SystemExit(f"{url} did not answer within {timeout:.0f} s")


class _Stop(Exception):
    """SIGTERM or SIGHUP arrived: stop like Ctrl-C does."""


def _stop(signum: int, frame: object) -> None:
    raise _Stop(signal.Signals(signum).name)


def default_data_dir() -> Path:
    """Where the demo keeps its data: the user's cache folder, never the repository (git would list it)."""
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "bonemesh-demo"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--data-dir", type=Path, default=None, help=f"default: {default_data_dir()}")
    parser.add_argument("--exit", action="store_true", help="stop everything after printing the links")
    args = parser.parse_args(argv)
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

    env = dict(os.environ)
    env.setdefault("BONEMESH_DATA_DIR", str((args.data_dir or default_data_dir()).resolve()))
    worker_log = Path(env["BONEMESH_DATA_DIR"]) / "worker.log"
    worker_log.parent.mkdir(parents=True, exist_ok=True)
    key = env.setdefault("BONEMESH_API_KEYS", DEV_API_KEY).split(",")[0].strip()
    procs: list[subprocess.Popen[bytes]] = []
    bin_dir = Path(sys.executable).parent
    bonemesh = str(bin_dir / "bonemesh") if (bin_dir / "bonemesh").exists() else "bonemesh"
    # kill -TERM (and SIGHUP) unwind like Ctrl-C, through the finally below, at any point of the run
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _stop)
    tmp = Path(tempfile.mkdtemp(prefix="bonemesh-redis-"))
    try:
        if "BONEMESH_REDIS_URL" not in env:
            port = _free_port()
            procs.append(
                subprocess.Popen(
                    [
                        _redis_server(),
                        "--port",
                        str(port),
                        "--bind",
                        "127.0.0.1",
                        "--save",
                        "",
                        "--appendonly",
                        "no",
                        "--dir",
                        str(tmp),
                    ],
                    stdout=subprocess.DEVNULL,
                )
            )
            env["BONEMESH_REDIS_URL"] = f"redis://127.0.0.1:{port}/0"
        base = f"http://127.0.0.1:{args.port}"
        procs.append(subprocess.Popen([bonemesh, "serve", "--port", str(args.port), "--log-level", "warning"], env=env))
        # the worker's banner, log and warnings go to its log file, not between the demo's lines
        with worker_log.open("ab") as log_file:
            procs.append(
                subprocess.Popen(
                    [bonemesh, "worker", "--loglevel", "WARNING"], env=env, stdout=log_file, stderr=subprocess.STDOUT
                )
            )
        _wait_http(f"{base}/readyz", procs, 60, worker_log)
        params = {"iso": 1150, "spacing": list(HEADSQ_SPACING_ZYX_MM)}
        body, ctype = _multipart(HEADSQ_ZIP, params)
        t0 = time.perf_counter()
        job = _request("POST", f"{base}/v1/jobs", key, body, ctype)
        print(f"job {job['id']} queued: the bundled VTK headsq CT head, params {json.dumps(params)}")  # noqa: T201
        stage = None
        while job["state"] in ("queued", "running"):
            time.sleep(0.5)
            job = _request("GET", f"{base}/v1/jobs/{job['id']}", key)
            if job["stage"] != stage:
                stage = job["stage"]
                print(f"  {time.perf_counter() - t0:6.1f} s  {job['state']:<9} {stage} {job['progress']:.0f}%")  # noqa: T201
        if job["state"] != "succeeded":
            print(f"job {job['state']}: {job['error']}", file=sys.stderr)  # noqa: T201
            print(f"the worker's log ({worker_log}):\n{_tail(worker_log)}", file=sys.stderr)  # noqa: T201
            return 1
        print(f"done in {time.perf_counter() - t0:.1f} s; downloads (no key needed, valid 1 h):")  # noqa: T201
        width = max(len(o["name"]) for o in job["outputs"])
        for o in job["outputs"]:
            tri = f"{o['triangles']:,} triangles" if o["triangles"] else ""
            print(f"  {o['name']:<{width}} {o['bytes']:>10,} B  {tri:<18} {o['url']}")  # noqa: T201
        print(f"page: {base}/  API: {base}/docs  (X-API-Key: {key}); the worker's log: {worker_log}")  # noqa: T201
        if not args.exit:
            print("serving; Ctrl-C (or kill -TERM) stops Redis, the API and the worker", flush=True)  # noqa: T201
            while True:
                signal.pause()
        return 0
    except (KeyboardInterrupt, _Stop) as exc:
        why = "Ctrl-C" if isinstance(exc, KeyboardInterrupt) else str(exc)
        print(f"stopping ({why}): Redis, the API and the worker", flush=True)  # noqa: T201
        return 0
    finally:
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):  # a second signal must not cut the cleanup short
            signal.signal(sig, signal.SIG_IGN)
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
